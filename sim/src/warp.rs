//! Rendering through a real lens: the board's shapes seen through `optics::Lens` (tilt,
//! distortion, lateral colour) with the print's imperfections (`print`).
//!
//! Same conventions as the ideal renderer (area integration on a sub-sample grid, the
//! Gaussian edge profile of the signed distance in image pixels), but distances are taken on
//! the board: each pixel centre is mapped back to the board exactly (per channel when the
//! channels' magnifications differ), the sub-samples through the local Jacobian (the map's
//! curvature within one pixel is < 1e-4 px), and a board distance is turned into image pixels
//! by the local scale along the edge's normal.

use crate::board::{Board, ClutterShape, Shape};
use crate::camera::CameraModel;
use crate::optics::Lens;
use crate::print::{InkDensity, RoughEdge};
use crate::render::{EdgeTable, View};
use nalgebra::Matrix2;
use std::sync::Arc;

/// The print of one board through one camera: rough edges per target and the ink field.
#[derive(Debug, Clone)]
pub struct Print {
    /// Per target: outer hole, outer rim, inner rim, inner hole (`None`: smooth or absent).
    edges: Vec<[Option<RoughEdge>; 4]>,
    density: Option<InkDensity>,
}

impl Print {
    pub fn new(board: &Board, cam: &CameraModel) -> Print {
        let edges = board
            .targets
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let radii = shape_radii(&t.outer, &t.inner);
                std::array::from_fn(|e| radii[e].and_then(|r| RoughEdge::new(cam, i, e, r)))
            })
            .collect();
        Print {
            edges,
            density: InkDensity::new(cam),
        }
    }

    /// The rough edge `edge` (0..4, see `RoughEdge::new`) of target `target`.
    pub fn edge(&self, target: usize, edge: usize) -> Option<&RoughEdge> {
        self.edges.get(target)?.get(edge)?.as_ref()
    }

    /// How far the printed offset (inner minus outer centre) lies from the designed one,
    /// µm: each shape's centre the least-squares one of its rough edges, weighted by their
    /// radii (an edge's length, hence what a fit of the shape reads of it).
    pub fn offset_shift_um(&self, board: &Board, target: usize) -> [f64; 2] {
        let t = &board.targets[target];
        let radii = shape_radii(&t.outer, &t.inner);
        let centre = |edges: [usize; 2]| {
            let (mut c, mut w) = ([0.0; 2], 0.0);
            for e in edges {
                if let (Some(r), Some(edge)) = (radii[e], self.edge(target, e)) {
                    let s = edge.centre_shift_um();
                    c = [c[0] + r * s[0], c[1] + r * s[1]];
                    w += r;
                }
            }
            if w > 0.0 {
                [c[0] / w, c[1] / w]
            } else {
                c
            }
        };
        let (o, i) = (centre([0, 1]), centre([2, 3]));
        [i[0] - o[0], i[1] - o[1]]
    }

    pub fn density(&self) -> Option<&InkDensity> {
        self.density.as_ref()
    }
}

/// Radii of a target's edges in `RoughEdge` order.
fn shape_radii(outer: &Shape, inner: &Shape) -> [Option<f64>; 4] {
    let (oh, or) = match *outer {
        Shape::Ring {
            inner_radius_um,
            outer_radius_um,
        } => (Some(inner_radius_um), outer_radius_um),
        Shape::Disk { radius_um } => (None, radius_um),
    };
    let (ir, ih) = match *inner {
        Shape::Ring {
            inner_radius_um,
            outer_radius_um,
        } => (outer_radius_um, Some(inner_radius_um)),
        Shape::Disk { radius_um } => (radius_um, None),
    };
    [oh, Some(or), Some(ir), ih]
}

#[derive(Debug, Clone)]
struct WDisk {
    centre_um: [f64; 2],
    radius_um: f64,
    sign: f64,
    /// (target, edge) of its roughness in `Print`.
    rough: Option<(usize, usize)>,
    /// Image box holding the shape's blurred edge, [x0, x1, y0, y1] px.
    bbox: [f64; 4],
}

#[derive(Debug, Clone)]
struct WRect {
    centre_um: [f64; 2],
    half_um: [f64; 2],
    bbox: [f64; 4],
}

/// Everything inked on the board for one view, on the board, with the lens that sees it.
pub(crate) struct WarpInk {
    lens: Lens,
    print: Arc<Print>,
    disks: Vec<WDisk>,
    rects: Vec<WRect>,
    /// Board point on the optical axis.
    axis_um: [f64; 2],
    /// The roll: a = R·(p − axis), R = [[cs, sn], [−sn, cs]].
    sn: f64,
    cs: f64,
    /// Principal point in image coordinates.
    pp: [f64; 2],
    /// Whether the channels see different geometry (lateral colour).
    per_channel: bool,
    margin: f64,
}

/// Image box of the board rectangle `centre ± half` (its boundary mapped through the lens in
/// every channel), grown by `margin` px.
fn image_box(w: &WarpInk, centre: [f64; 2], half: [f64; 2], margin: f64) -> [f64; 4] {
    let mut b = [
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    ];
    for k in 0..64 {
        let t = k as f64 / 16.0;
        let (side, f) = ((t as usize) % 4, 2.0 * t.fract() - 1.0);
        let (x, y) = match side {
            0 => (f, -1.0),
            1 => (1.0, f),
            2 => (-f, 1.0),
            _ => (-1.0, -f),
        };
        let p = [centre[0] + x * half[0], centre[1] + y * half[1]];
        for ch in 0..3 {
            let q = w.to_image(ch, p);
            b = [
                b[0].min(q[0]),
                b[1].max(q[0]),
                b[2].min(q[1]),
                b[3].max(q[1]),
            ];
        }
    }
    [b[0] - margin, b[1] + margin, b[2] - margin, b[3] + margin]
}

impl WarpInk {
    pub(crate) fn new(board: &Board, cam: &CameraModel, view: &View, print: Arc<Print>) -> WarpInk {
        let s = cam.scale_um_per_px;
        let (cx, cy) = (cam.width as f64 / 2.0, cam.height as f64 / 2.0);
        let (sn, cs) = view.roll_rad.sin_cos();
        let mut w = WarpInk {
            lens: Lens::at_depth(cam, view.depth_um),
            print,
            disks: Vec::new(),
            rects: Vec::new(),
            axis_um: [view.camera_um[0] + s * cx, view.camera_um[1] + s * cy],
            sn,
            cs,
            pp: [cx - 0.5, cy - 0.5],
            per_channel: cam.lateral_colour_r != 0.0 || cam.lateral_colour_b != 0.0,
            margin: 5.0 * cam.psf_sigma_px + 2.0,
        };
        // Rough edges stray a few RMS from the nominal radius.
        let slack = 5.0 * cam.edge_roughness_um;
        for (ti, t) in board.targets.iter().enumerate() {
            let radii = shape_radii(&t.outer, &t.inner);
            let signs = [-1.0, 1.0, 1.0, -1.0];
            for e in 0..4 {
                let Some(r) = radii[e] else { continue };
                let centre = if e < 2 {
                    t.centre_um
                } else {
                    t.inner_centre_um()
                };
                let bbox = image_box(&w, centre, [r + slack; 2], w.margin);
                w.disks.push(WDisk {
                    centre_um: centre,
                    radius_um: r,
                    sign: signs[e],
                    rough: w.print.edge(ti, e).map(|_| (ti, e)),
                    bbox,
                });
            }
        }
        for c in &board.clutter {
            match c.shape {
                ClutterShape::Disk { radius_um } => {
                    let bbox = image_box(&w, c.centre_um, [radius_um; 2], w.margin);
                    w.disks.push(WDisk {
                        centre_um: c.centre_um,
                        radius_um,
                        sign: 1.0,
                        rough: None,
                        bbox,
                    })
                }
                ClutterShape::Rect {
                    width_um,
                    height_um,
                } => {
                    let half = [width_um / 2.0, height_um / 2.0];
                    let bbox = image_box(&w, c.centre_um, half, w.margin);
                    w.rects.push(WRect {
                        centre_um: c.centre_um,
                        half_um: half,
                        bbox,
                    })
                }
            }
        }
        w
    }

    /// Image point (pixel centres at integers) of board point `p_um` in `channel`.
    pub(crate) fn to_image(&self, channel: usize, p_um: [f64; 2]) -> [f64; 2] {
        let (dx, dy) = (p_um[0] - self.axis_um[0], p_um[1] - self.axis_um[1]);
        let a = [self.cs * dx + self.sn * dy, -self.sn * dx + self.cs * dy];
        let o = self.lens.forward(channel, a);
        [self.pp[0] + o[0], self.pp[1] + o[1]]
    }

    /// Board point seen at image point (u, v) in `channel`, and d(board)/d(image) (µm/px).
    fn to_board(&self, channel: usize, u: f64, v: f64) -> ([f64; 2], Matrix2<f64>) {
        let (a, j) = self.lens.inverse(channel, [u - self.pp[0], v - self.pp[1]]);
        // p = axis + Rᵀ·a.
        let rt = Matrix2::new(self.cs, -self.sn, self.sn, self.cs);
        let p = [
            self.axis_um[0] + self.cs * a[0] - self.sn * a[1],
            self.axis_um[1] + self.sn * a[0] + self.cs * a[1],
        ];
        (p, rt * j)
    }

    /// Indices of the disks and rectangles whose box holds row `v`.
    pub(crate) fn near_row(&self, v: f64) -> (Vec<usize>, Vec<usize>) {
        let d = (0..self.disks.len())
            .filter(|&i| v >= self.disks[i].bbox[2] && v <= self.disks[i].bbox[3])
            .collect();
        let r = (0..self.rects.len())
            .filter(|&i| v >= self.rects[i].bbox[2] && v <= self.rects[i].bbox[3])
            .collect();
        (d, r)
    }

    /// Those of `near` whose box holds column `u`.
    pub(crate) fn near_col(
        &self,
        near: &[usize],
        rects: &[usize],
        u: f64,
        out: &mut Vec<usize>,
        out_r: &mut Vec<usize>,
    ) {
        out.clear();
        out.extend(
            near.iter()
                .copied()
                .filter(|&i| u >= self.disks[i].bbox[0] && u <= self.disks[i].bbox[1]),
        );
        out_r.clear();
        out_r.extend(
            rects
                .iter()
                .copied()
                .filter(|&i| u >= self.rects[i].bbox[0] && u <= self.rects[i].bbox[1]),
        );
    }

    /// The ink of pixel (u, v) per channel: its coverage times the print's density, blurred
    /// whole by the lens (`InkTaylor`) and area-integrated.
    pub(crate) fn ink(
        &self,
        near: &[usize],
        rects: &[usize],
        u: f64,
        v: f64,
        cam: &CameraModel,
        edge: &EdgeTable,
    ) -> [f64; 3] {
        let var = cam.psf_sigma_px.max(1e-3).powi(2);
        let taylor = |p: [f64; 2], j: &Matrix2<f64>| {
            self.print.density().map(|d| InkTaylor::at(d, p, j, var))
        };
        let (p, j) = self.to_board(1, u, v);
        let green = self.channel_ink(near, rects, (p, &j), cam, edge, taylor(p, &j));
        if !self.per_channel {
            return [green; 3];
        }
        let mut ink = [green; 3];
        for ch in [0, 2] {
            let (p, j) = self.to_board(ch, u, v);
            ink[ch] = self.channel_ink(near, rects, (p, &j), cam, edge, taylor(p, &j));
        }
        ink
    }

    /// The shapes about the pixel whose centre sees board point `p` with Jacobian `j`: those
    /// whose edge is within the blur's reach (evaluated on the sub-sample grid), and the
    /// coverage of those wholly over or off it.
    fn near_edges(
        &self,
        near: &[usize],
        rects: &[usize],
        (p, j): ([f64; 2], &Matrix2<f64>),
        cam: &CameraModel,
    ) -> NearEdges {
        let sigma = cam.psf_sigma_px.max(1e-3);
        let (band, close) = (5.0 * sigma + 0.75, 2.0 * sigma + 0.1);
        let mut out = NearEdges::default();
        for &i in near {
            let d = &self.disks[i];
            let e = [p[0] - d.centre_um[0], p[1] - d.centre_um[1]];
            // (`hypot` is a slow libm call; the squares cannot overflow here.)
            let rho = (e[0] * e[0] + e[1] * e[1]).sqrt().max(1e-9);
            let r = d.radius_um
                + d.rough
                    .and_then(|(t, k)| self.print.edge(t, k))
                    .map_or(0.0, |re| re.at(e[0], e[1]));
            let (nx, ny) = (e[0] / rho, e[1] / rho);
            // d(distance)/d(image) = nᵀ·J: µm per px along the steepest direction.
            let gx = nx * j[(0, 0)] + ny * j[(1, 0)];
            let gy = nx * j[(0, 1)] + ny * j[(1, 1)];
            let k = 1.0 / (gx * gx + gy * gy).sqrt();
            let dist = (rho - r) * k;
            if dist.abs() < band && out.n_disks < MAX_ACTIVE {
                out.close |= dist.abs() < close;
                out.disks[out.n_disks] = (i, e, r, k, [gx * k, gy * k]);
                out.n_disks += 1;
            } else if dist < 0.0 {
                out.flat += d.sign;
            }
        }
        let (kx, ky) = row_scales(j);
        for &i in rects {
            let r = &self.rects[i];
            let e = [p[0] - r.centre_um[0], p[1] - r.centre_um[1]];
            let dx = (e[0].abs() - r.half_um[0]) * kx;
            let dy = (e[1].abs() - r.half_um[1]) * ky;
            let reach = (dx.abs() < band || dy.abs() < band) && dx < band && dy < band;
            if reach && out.n_rects < MAX_ACTIVE {
                out.close |= dx.abs() < close || dy.abs() < close;
                out.rects[out.n_rects] = (i, e);
                out.n_rects += 1;
            } else if dx < 0.0 && dy < 0.0 {
                out.flat += 1.0;
            }
        }
        out
    }

    /// The ink of the pixel whose centre sees board point `p` with Jacobian `j`: coverage
    /// alone on an even print, else the blurred inked density (`InkTaylor::sample`),
    /// area-integrated on the sub-sample grid.
    fn channel_ink(
        &self,
        near: &[usize],
        rects: &[usize],
        (p, j): ([f64; 2], &Matrix2<f64>),
        cam: &CameraModel,
        edge: &EdgeTable,
        density: Option<InkTaylor>,
    ) -> f64 {
        let at = self.near_edges(near, rects, (p, j), cam);
        if at.n_disks == 0 && at.n_rects == 0 {
            let c = at.flat.clamp(0.0, 1.0);
            return density.map_or(c, |t| c * t.flat());
        }
        let n = if at.close {
            cam.supersample.max(1)
        } else {
            cam.supersample.clamp(1, 3)
        };
        let step = 1.0 / n as f64;
        let (kx, ky) = row_scales(j);
        let mut sum = 0.0;
        for sj in 0..n {
            let dv = -0.5 + (sj as f64 + 0.5) * step;
            for si in 0..n {
                let du = -0.5 + (si as f64 + 0.5) * step;
                // Board offset of this sub-sample from the pixel centre's board point.
                let ox = j[(0, 0)] * du + j[(0, 1)] * dv;
                let oy = j[(1, 0)] * du + j[(1, 1)] * dv;
                let mut edges = EdgeSum {
                    c: at.flat,
                    ..EdgeSum::default()
                };
                for &(i, e, r, k, m) in &at.disks[..at.n_disks] {
                    let (x, y) = (e[0] + ox, e[1] + oy);
                    let d = ((x * x + y * y).sqrt() - r) * k;
                    edges.add(self.disks[i].sign, d, m, edge, density.is_some());
                }
                for &(i, e) in &at.rects[..at.n_rects] {
                    // (Clutter is not measured: its edges take the density unblurred.)
                    let rc = &self.rects[i];
                    let ex = edge.at(((e[0] + ox).abs() - rc.half_um[0]) * kx);
                    let ey = edge.at(((e[1] + oy).abs() - rc.half_um[1]) * ky);
                    edges.c += ex * ey;
                }
                sum += match density {
                    Some(t) => t.sample(&edges, [du, dv]),
                    None => edges.c.clamp(0.0, 1.0),
                };
            }
        }
        sum * step * step
    }
}

/// Shapes a pixel's sub-samples evaluate at most.
const MAX_ACTIVE: usize = 8;

/// A disk whose edge is within reach of a pixel: (index, offset from its centre µm,
/// effective radius µm, px per µm along the normal, the normal in the image).
type NearDisk = (usize, [f64; 2], f64, f64, [f64; 2]);

/// The shapes about one pixel (`WarpInk::near_edges`).
#[derive(Debug, Default)]
struct NearEdges {
    disks: [NearDisk; MAX_ACTIVE],
    n_disks: usize,
    /// Rectangles within reach: (index, offset from centre µm).
    rects: [(usize, [f64; 2]); MAX_ACTIVE],
    n_rects: usize,
    /// The coverage of the shapes wholly over the pixel.
    flat: f64,
    /// An edge within two blur widths: the full sub-sample grid.
    close: bool,
}

/// The blurred coverage at one sub-sample: its value, and for an uneven print its image
/// gradient `Σ sign·E′·m` and `Σ sign·E″·(m·H·m)`'s parts (E the edge profile, m an edge's
/// normal in the image), which the density's blur needs.
#[derive(Debug, Default, Clone, Copy)]
struct EdgeSum {
    c: f64,
    grad: [f64; 2],
    /// Per edge: sign·E″ and its normal, for the density's Hessian.
    curv: [(f64, [f64; 2]); MAX_ACTIVE],
    n_curv: usize,
}

impl EdgeSum {
    #[inline]
    fn add(&mut self, sign: f64, d: f64, m: [f64; 2], edge: &EdgeTable, slopes: bool) {
        if !slopes {
            self.c += sign * edge.at(d);
            return;
        }
        let (v, slope) = edge.at_slope(d);
        self.c += sign * v;
        self.grad = [
            self.grad[0] + sign * slope * m[0],
            self.grad[1] + sign * slope * m[1],
        ];
        if self.n_curv < self.curv.len() {
            // E″ = −(d/σ²)·E′ for the Gaussian profile; σ² is applied in `sample`.
            self.curv[self.n_curv] = (-sign * d * slope, m);
            self.n_curv += 1;
        }
    }
}

/// The print's density about one pixel, in image px: ε blurred by the lens at the pixel's
/// centre, its gradient and Hessian (xx, xy, yy), and the lens's blur variance σ². A real
/// lens blurs the inked density `(1 + ε)·f` whole, f the printed coverage. For one plane
/// wave of ε across a straight edge the blur is exact in closed form, `e^{−σ²k²/2}` times
/// the edge profile at a complex-shifted distance; to second order in σ²k, summed over the
/// waves, `G∗((1+ε)f) = C + ε̃·C + σ²·∇ε̃·∇C + ½σ⁴·H̃:∇∇C`, C = G∗f, ε̃ = G∗ε. The
/// first-order term moves an edge by σ²·∂ε/∂n; it is what a renderer that takes the
/// density at the pixel leaves out (checked against a brute-force convolution in the
/// tests). The pixel's area is integrated on the sub-samples.
#[derive(Debug, Clone, Copy)]
pub(crate) struct InkTaylor {
    e: f64,
    g: [f64; 2],
    h: [f64; 3],
    var: f64,
}

impl InkTaylor {
    /// At board point `p` seen through `j` (board µm per image px).
    pub(crate) fn at(d: &InkDensity, p: [f64; 2], j: &Matrix2<f64>, var: f64) -> InkTaylor {
        let jt = [[j[(0, 0)], j[(1, 0)]], [j[(0, 1)], j[(1, 1)]]];
        let (e, g, h) = d.blurred(p, jt, var);
        InkTaylor { e, g, h, var }
    }

    /// A pixel all inked: the blurred density averaged over the pixel.
    fn flat(&self) -> f64 {
        1.0 + self.e + (self.h[0] + self.h[2]) / 24.0
    }

    /// The blurred inked density at the sub-sample `o` px from the pixel's centre.
    #[inline]
    fn sample(&self, s: &EdgeSum, o: [f64; 2]) -> f64 {
        let [hxx, hxy, hyy] = self.h;
        let ho = [hxx * o[0] + hxy * o[1], hxy * o[0] + hyy * o[1]];
        let e = self.e + self.g[0] * o[0] + self.g[1] * o[1] + 0.5 * (o[0] * ho[0] + o[1] * ho[1]);
        let g = [self.g[0] + ho[0], self.g[1] + ho[1]];
        let c = s.c.clamp(0.0, 1.0);
        if c != s.c {
            // Overlapping ink: no edge to move.
            return c * (1.0 + e);
        }
        let curv: f64 = s.curv[..s.n_curv]
            .iter()
            .map(|&(e2, m)| e2 * (hxx * m[0] * m[0] + 2.0 * hxy * m[0] * m[1] + hyy * m[1] * m[1]))
            .sum();
        (1.0 + e) * c + self.var * (g[0] * s.grad[0] + g[1] * s.grad[1]) + 0.5 * self.var * curv
    }
}

/// Image px per board µm along the board's x and y (rows of the Jacobian).
#[inline]
fn row_scales(j: &Matrix2<f64>) -> (f64, f64) {
    let n = |a: f64, b: f64| 1.0 / (a * a + b * b).sqrt();
    (n(j[(0, 0)], j[(0, 1)]), n(j[(1, 0)], j[(1, 1)]))
}

/// One row of expected DN through the lens (see `render::render_rows`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn render_row(
    board: &Board,
    cam: &CameraModel,
    ink: &WarpInk,
    edge: &EdgeTable,
    x0: u32,
    w: u32,
    v: f64,
    line: &mut [f32],
    light: f64,
) {
    let (near, near_r) = ink.near_row(v);
    let (mut nx, mut nr) = (
        Vec::with_capacity(near.len()),
        Vec::with_capacity(near_r.len()),
    );
    for col in 0..w {
        let u = (x0 + col) as f64;
        ink.near_col(&near, &near_r, u, &mut nx, &mut nr);
        let inked = if nx.is_empty() && nr.is_empty() {
            [0.0; 3]
        } else {
            ink.ink(&nx, &nr, u, v, cam, edge)
        };
        let lum = cam.white_dn * light * cam.illumination(u, v);
        for c in 0..3 {
            let refl = board.paper_rgb[c] - (board.paper_rgb[c] - board.ink_rgb[c]) * inked[c];
            line[(col * 3) as usize + c] = (lum * refl) as f32;
        }
    }
}

/// Image box [x0, x1, y0, y1] of every shape of the board (targets by their outer edge,
/// clutter), in px, grown by the blur's margin: the boxes `SceneRenderer` re-renders.
pub(crate) fn shape_boxes(ink: &WarpInk, board: &Board) -> Vec<[f64; 4]> {
    let mut out = Vec::new();
    let mut k = 0;
    for t in &board.targets {
        let n = shape_radii(&t.outer, &t.inner).iter().flatten().count();
        let boxes = &ink.disks[k..k + n];
        out.push(boxes.iter().fold(
            [
                f64::INFINITY,
                f64::NEG_INFINITY,
                f64::INFINITY,
                f64::NEG_INFINITY,
            ],
            |b, d| {
                [
                    b[0].min(d.bbox[0]),
                    b[1].max(d.bbox[1]),
                    b[2].min(d.bbox[2]),
                    b[3].max(d.bbox[3]),
                ]
            },
        ));
        k += n;
    }
    out.extend(ink.disks[k..].iter().map(|d| d.bbox));
    out.extend(ink.rects.iter().map(|r| r.bbox));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A large-scale view of the paper board's first target through a tilted lens, the
    /// print's density 8 % RMS over 1.5 mm (≈ 5 px): edges 20–60 px in radius, so the blurred
    /// circles are near their half-planes.
    fn lens_on_target() -> (Board, CameraModel, WarpInk, [f64; 2]) {
        let board = Board::paper();
        let cam = CameraModel {
            scale_um_per_px: 283.0,
            psf_sigma_px: 0.8,
            supersample: 8,
            tilt_x_deg: 2.0,
            ink_density_rms: 0.08,
            ink_density_corr_um: 1500.0,
            ..CameraModel::default()
        };
        let c = board.targets[0].centre_um;
        let s = cam.scale_um_per_px;
        let view = View::at([c[0] - 320.0 * s, c[1] - 240.0 * s]);
        let print = Arc::new(Print::new(&board, &cam));
        let ink = WarpInk::new(&board, &cam, &view, print);
        let centre = ink.to_image(1, c);
        (board, cam, ink, centre)
    }

    /// What blurring the inked density adds beyond `(1 + ε(pixel centre))·coverage`, at pixel
    /// (u, v), by brute force: the sharp print `(1 + ε)·f` on a grid 1/24 px apart, weighted
    /// by the pixel's box convolved with the PSF.
    fn brute_force_excess(ink: &WarpInk, cam: &CameraModel, u: f64, v: f64) -> f64 {
        let (sigma, h) = (cam.psf_sigma_px, 1.0 / 24.0);
        let phi = |x: f64| 0.5 * libm::erfc(-x / (std::f64::consts::SQRT_2 * sigma));
        let reach = 0.5 + 5.0 * sigma;
        let n = (reach / h).ceil() as i64;
        let w: Vec<(f64, f64)> = (-n..=n)
            .map(|i| {
                let t = i as f64 * h;
                (t, h * (phi(t + 0.5) - phi(t - 0.5)))
            })
            .collect();
        let density = ink.print.density().unwrap();
        let e0 = density.at(ink.to_board(1, u, v).0);
        let mut inked = 0.0;
        for &(ty, wy) in &w {
            for &(tx, wx) in &w {
                let p = ink.to_board(1, u + tx, v + ty).0;
                let f: f64 = ink
                    .disks
                    .iter()
                    .map(|d| {
                        let r = ((p[0] - d.centre_um[0]).powi(2) + (p[1] - d.centre_um[1]).powi(2))
                            .sqrt();
                        if r < d.radius_um {
                            d.sign
                        } else {
                            0.0
                        }
                    })
                    .sum::<f64>()
                    .clamp(0.0, 1.0);
                inked += wx * wy * (density.at(p) - e0) * f;
            }
        }
        // Σw(1+ε)f − (1+ε₀)Σwf: the circles' own blur (the renderer's half-planes) cancels.
        inked
    }

    /// The renderer's excess at (u, v): its ink minus `(1 + ε₀)` times its even coverage.
    fn rendered_excess(ink: &WarpInk, cam: &CameraModel, u: f64, v: f64) -> f64 {
        let edge = EdgeTable::new(cam.psf_sigma_px);
        let (near, near_r) = ink.near_row(v);
        let (mut nx, mut nr) = (Vec::new(), Vec::new());
        ink.near_col(&near, &near_r, u, &mut nx, &mut nr);
        let uneven = ink.ink(&nx, &nr, u, v, cam, &edge)[1];
        let (p, j) = ink.to_board(1, u, v);
        let even = ink.channel_ink(&nx, &nr, (p, &j), cam, &edge, None);
        uneven - (1.0 + ink.print.density().unwrap().at(p)) * even
    }

    #[test]
    fn the_lens_blurs_the_inked_density_whole() {
        let (_board, cam, ink, c) = lens_on_target();
        let s = cam.scale_um_per_px;
        // Across the disk's edge, the ring's outer edge, and inside the disk, on four rays.
        let radii: Vec<f64> = (-3..=3)
            .flat_map(|d| [6000.0 / s + d as f64, 17000.0 / s + d as f64])
            .chain([8.0])
            .collect();
        let (mut worst, mut largest, mut n) = (0.0f64, 0.0f64, 0);
        for theta in [0.3f64, 1.9, 3.5, 5.0] {
            for &r in &radii {
                let (u, v) = (
                    (c[0] + r * theta.cos()).round(),
                    (c[1] + r * theta.sin()).round(),
                );
                let want = brute_force_excess(&ink, &cam, u, v);
                let got = rendered_excess(&ink, &cam, u, v);
                worst = worst.max((got - want).abs());
                largest = largest.max(want.abs());
                n += 1;
            }
        }
        // A renderer that takes ε at the pixel times the coverage has no excess: it is off
        // by `largest` (8.1e-3 of the ink's depth). This one is off by 1.1 % of it (8.7e-5,
        // the same with a grid twice as fine: the half-plane edges' curvature and the
        // third order); with the density's blur to first order only (ε unblurred inside),
        // by 4 %.
        assert!(
            largest > 5e-3,
            "the blur adds {largest:.2e} at most ({n} px)"
        );
        assert!(
            worst < 0.02 * largest,
            "off by {worst:.2e} of {largest:.2e}"
        );
    }
}
