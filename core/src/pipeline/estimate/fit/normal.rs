//! The model's normal equations, `JᵀJ`, `Jᵀr` and the cost, over a window's pixels.
//!
//! This is where the fit spends its time (~2 000 pixels a frame, ~8 100 on a k = 10 fine
//! grid, one to four passes each). The pixels go eight at a time through a branch-free
//! model (`edge.rs`) evaluated in `f32` into per-lane `f32` sums of the upper triangle,
//! which the compiler turns into vector code; on a CPU with AVX2 (checked at run time) the
//! same code is compiled again for its 8-wide registers. Both give the same bits: no fused
//! multiply-adds, and the same operations in the same order.
//!
//! Why `f32` is enough: positions are taken from the window's middle (|x| < 300 fine px,
//! a rounding of 2e-5 px), a pixel's value and model agree to ~1e-4 DN against ~2.5 DN of
//! noise, and a lane sums at most ~1 000 terms (relative error ~1e-6 on `JᵀJ`, far below
//! its own sampling error). The cost, whose changes decide the steps, is summed in `f64`.
//! Against the `f64` per-pixel form (the tests' reference) the minimum moves by < 1e-5 px.

use super::edge::{edge, flat_edge, Real, FLAT};
use super::{
    Problem, B0, BX, BY, C, CI, CXI, CXO, CYI, CYO, GRADIENTS, HOLE, MAXP, NC, RI, RIH, RIM, S,
};

/// Pixels evaluated together.
const LANES: usize = 8;
type Lanes = [f32; LANES];

/// Normal equations and cost at one parameter vector.
pub(super) struct Normal {
    pub h: [[f64; MAXP]; MAXP],
    pub g: [f64; MAXP],
    pub cost: f64,
    pub n: usize,
}

/// Up to eight pixels waiting to be evaluated: positions (from the window's middle) and
/// values.
#[derive(Default)]
struct Batch {
    x: Lanes,
    y: Lanes,
    v: Lanes,
    len: usize,
}

/// Per-lane running sums (the upper triangle of `JᵀJ`), folded into a [`Normal`] at the end.
struct Sums {
    /// The parameters summed (in order), `nfree` of them.
    free: [usize; MAXP],
    nfree: usize,
    h: [[Lanes; MAXP]; MAXP],
    g: [Lanes; MAXP],
    cost: [f64; LANES],
    n: usize,
}

impl Normal {
    /// These sums with the contrast gradients held: their rows and columns zero, as the
    /// even-ink model's own pass gives them (the other sums are the same bits: each pair
    /// of parameters is summed on its own, over the same pixels in the same order).
    pub(super) fn held(&self) -> Normal {
        let mut n = Normal {
            h: self.h,
            g: self.g,
            cost: self.cost,
            n: self.n,
        };
        for a in GRADIENTS {
            n.g[a] = 0.0;
            for b in 0..MAXP {
                n.h[a][b] = 0.0;
                n.h[b][a] = 0.0;
            }
        }
        n
    }
}

/// One pixel's model in `f64`: the Jacobian row, the paper level L and the shade
/// `1 − c_o·cov_o − c_i·cov_i` (the model is `L·shade`).
pub(super) struct Row {
    pub j: [f64; MAXP],
    pub l: f64,
    pub shade: f64,
}

impl Problem<'_> {
    /// [`Row`] at (`fx`, `fy`) from the window's middle, with value `v`.
    pub(super) fn row_f64(&self, p: &[f64; MAXP], fx: f64, fy: f64, v: f64) -> Row {
        let mut q = *p;
        for (i, axis) in [(CXO, 0), (CYO, 1), (CXI, 0), (CYI, 1)] {
            q[i] = p[i] - self.mid[axis];
        }
        let (j, _) = self.pixel::<f64, true, true>(&q, fx, fy, v);
        let (bx, by) = (fx * self.inv_half, fy * self.inv_half);
        Row {
            j,
            l: p[B0] + p[BX] * bx + p[BY] * by,
            shade: j[B0],
        }
    }

    pub(super) fn normal(&self, p: &[f64; MAXP]) -> Normal {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2, checked just above.
            return unsafe { self.normal_avx2(p) };
        }
        self.normal_lanes(p)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn normal_avx2(&self, p: &[f64; MAXP]) -> Normal {
        self.normal_lanes(p)
    }

    /// Every pixel of the window (at the problem's stride) within reach of the guessed
    /// centre, in batches of eight.
    #[inline(always)]
    fn normal_lanes(&self, p: &[f64; MAXP]) -> Normal {
        let mut free = [0; MAXP];
        let mut nfree = 0;
        for a in (0..self.np).filter(|a| self.planes || !GRADIENTS.contains(a)) {
            free[nfree] = a;
            nfree += 1;
        }
        let mut sums = Sums {
            free,
            nfree,
            h: [[[0.0; LANES]; MAXP]; MAXP],
            g: [[0.0; LANES]; MAXP],
            cost: [0.0; LANES],
            n: 0,
        };
        let q = self.relative(p);
        let classes = Classes::new(self, p, &free[..nfree]);
        let mut batches: [Batch; 4] = Default::default();
        let reach2 = self.win.reach * self.win.reach;
        for y in (self.win.y0..self.win.y1).step_by(self.step) {
            let fy = y as f64;
            let ry = fy - self.reach_centre[1];
            let row = &self.plane.data[y * self.plane.width..(y + 1) * self.plane.width];
            for x in (self.win.x0..self.win.x1).step_by(self.step) {
                let fx = x as f64;
                let rx = fx - self.reach_centre[0];
                if rx * rx + ry * ry > reach2 {
                    continue;
                }
                let class = classes.of(fx, fy);
                let batch = &mut batches[class];
                let l = batch.len;
                batch.x[l] = (fx - self.mid[0]) as f32;
                batch.y[l] = (fy - self.mid[1]) as f32;
                batch.v[l] = row[x];
                batch.len += 1;
                if batch.len == LANES {
                    self.add_class(class, &q, batch, &mut sums, &classes);
                    batch.len = 0;
                }
            }
        }
        for (class, batch) in batches.iter().enumerate() {
            if batch.len > 0 {
                self.add_class(class, &q, batch, &mut sums, &classes);
            }
        }
        sums.fold()
    }

    /// The parameters in `f32`, the centres from the window's middle.
    fn relative(&self, p: &[f64; MAXP]) -> [f32; MAXP] {
        let mut q = p.map(|v| v as f32);
        for (i, axis) in [(CXO, 0), (CYO, 1), (CXI, 0), (CYI, 1)] {
            q[i] = (p[i] - self.mid[axis]) as f32;
        }
        q
    }

    /// A batch of one class through the model compiled for it.
    #[inline(always)]
    fn add_class(&self, class: usize, q: &[f32; MAXP], b: &Batch, sums: &mut Sums, c: &Classes) {
        let free = &c.free[class][..c.nfree[class]];
        match class {
            0 => self.add_batch::<false, false>(q, b, sums, free),
            OUTER => self.add_batch::<true, false>(q, b, sums, free),
            INNER => self.add_batch::<false, true>(q, b, sums, free),
            _ => self.add_batch::<true, true>(q, b, sums, free),
        }
    }

    /// The model, its Jacobian rows and residuals for one batch, added to the sums of the
    /// parameters `free` (those the class's Jacobian rows can move). Lanes past
    /// `batch.len` are evaluated at whatever they hold and weighted 0.
    #[inline(always)]
    fn add_batch<const O: bool, const I: bool>(
        &self,
        q: &[f32; MAXP],
        batch: &Batch,
        sums: &mut Sums,
        free: &[usize],
    ) {
        let mut j = [[0.0; LANES]; MAXP];
        let mut r = [0.0; LANES];
        for l in 0..LANES {
            let w = if l < batch.len { 1.0 } else { 0.0 };
            let (row, res) = self.pixel::<f32, O, I>(q, batch.x[l], batch.y[l], batch.v[l]);
            for (ja, va) in j.iter_mut().zip(row) {
                ja[l] = va * w;
            }
            r[l] = res * w;
        }
        sums.n += batch.len;
        for (c, &rl) in sums.cost.iter_mut().zip(&r) {
            *c += rl as f64 * rl as f64;
        }
        // Only the parameters the fit moves and this class's rows touch: the rest are zero.
        for (i, &a) in free.iter().enumerate() {
            for (g, (&ja, &rl)) in sums.g[a].iter_mut().zip(j[a].iter().zip(&r)) {
                *g += ja * rl;
            }
            for &b in &free[i..] {
                for (h, (&ja, &jb)) in sums.h[a][b].iter_mut().zip(j[a].iter().zip(&j[b])) {
                    *h += ja * jb;
                }
            }
        }
    }

    /// One pixel's Jacobian row (`∂model/∂p`) and residual `v − model`, at position
    /// (`fx`, `fy`) from the window's middle, the centres in `p` likewise. Where the outer
    /// (`O` false) or inner (`I` false) edges are known flat, their coverage is selected
    /// without the special functions and their slopes are 0, as [`edge`] gives them there.
    #[inline(always)]
    fn pixel<T: Real, const O: bool, const I: bool>(
        &self,
        p: &[T; MAXP],
        fx: T,
        fy: T,
        v: T,
    ) -> ([T; MAXP], T) {
        let c = T::c;
        // Uniform switches as factors, so that every lane runs the same code.
        let ring_inner = c(if self.np == MAXP { 1.0 } else { 0.0 });
        let free_gradients = c(if self.planes { 1.0 } else { 0.0 });
        let inv_s = c(1.0) / p[S];
        let (ro, dro_x, dro_y) = self.rho(fx - p[CXO], fy - p[CYO]);
        let (ri, dri_x, dri_y) = self.rho(fx - p[CXI], fy - p[CYI]);
        let at = |active: bool, d: T| {
            if active {
                edge(d, inv_s)
            } else {
                flat_edge(d)
            }
        };
        let (e_rim, d_rim) = at(O, ro - p[RIM]);
        let (e_hole, d_hole) = at(O, ro - p[HOLE]);
        let (e_in, d_in) = at(I, ri - p[RI]);
        let (e_ih, d_ih) = at(I, ri - p[RIH]);
        let (e_ih, d_ih) = (e_ih * ring_inner, d_ih * ring_inner);
        let (cov_o, cov_i) = (e_rim - e_hole, e_in - e_ih);
        let inv_half = c(self.inv_half);
        let (bx, by) = (fx * inv_half, fy * inv_half);
        let l = p[B0] + p[BX] * bx + p[BY] * by;
        let c_o = p[C] + p[C + 1] * bx + p[C + 2] * by;
        let c_i = p[CI] + p[CI + 1] * bx + p[CI + 2] * by;
        let shade = c(1.0) - c_o * cov_o - c_i * cov_i;
        let mut j = [c(0.0); MAXP];
        j[B0] = shade;
        j[BX] = bx * shade;
        j[BY] = by * shade;
        let mono = [c(1.0), bx * free_gradients, by * free_gradients];
        for (at, cov) in [(C, cov_o), (CI, cov_i)] {
            for (jc, m) in j[at..at + NC].iter_mut().zip(mono) {
                *jc = -l * cov * m;
            }
        }
        let (lco, lci) = (-l * c_o, -l * c_i);
        let douter = d_rim - d_hole;
        j[CXO] = lco * douter * dro_x;
        j[CYO] = lco * douter * dro_y;
        j[RIM] = lco * -d_rim;
        j[HOLE] = lco * d_hole;
        let dinner = d_in - d_ih;
        j[CXI] = lci * dinner * dri_x;
        j[CYI] = lci * dinner * dri_y;
        j[RI] = lci * -d_in;
        j[RIH] = lci * d_ih;
        // dE/ds = −E'(d)·d/s.
        let ds_o = -(d_rim * (ro - p[RIM]) - d_hole * (ro - p[HOLE])) * inv_s;
        let ds_i = -(d_in * (ri - p[RI]) - d_ih * (ri - p[RIH])) * inv_s;
        j[S] = lco * ds_o + lci * ds_i;
        (j, v - l * shade)
    }
}

/// Which edges can be other than flat at a pixel: bit [`OUTER`] the ring's, bit [`INNER`]
/// the inner shape's. Decided from the distance to each shape's centre with a margin, so
/// that a pixel put in a class without an edge has that edge flat for certain (an edge
/// that is flat anyway is also evaluated right by [`edge`]).
const OUTER: usize = 1;
const INNER: usize = 2;

/// The classes' bounds at one parameter vector, and each class's free parameters.
struct Classes {
    centre: [[f64; 2]; 2],
    /// The problem's rectifying map: the radii are the rectified frame's.
    rectify: [[f64; 2]; 2],
    /// Per shape, squared radii: flat inside `lo2`, flat outside `hi2` (`lo2` < 0: never
    /// flat inside).
    lo2: [f64; 2],
    hi2: [f64; 2],
    free: [[usize; MAXP]; 4],
    nfree: [usize; 4],
}

impl Classes {
    fn new(prob: &Problem, p: &[f64; MAXP], free: &[usize]) -> Classes {
        // FLAT blur widths, less a margin far wider than the f32 model's roundings.
        let flat = FLAT * p[S] + 1e-3 * p[S].max(1.0);
        let bounds = |radii: &[f64]| {
            let lo = radii.iter().copied().fold(f64::INFINITY, f64::min) - flat;
            let hi = radii.iter().copied().fold(0.0, f64::max) + flat;
            (if lo > 0.0 { lo * lo } else { -1.0 }, hi * hi)
        };
        let (lo_o, hi_o) = bounds(&[p[HOLE], p[RIM]]);
        let inner: &[f64] = if prob.np == MAXP {
            &[p[RI], p[RIH]]
        } else {
            &[p[RI]]
        };
        let (lo_i, hi_i) = bounds(inner);
        let mut out = Classes {
            centre: [[p[CXO], p[CYO]], [p[CXI], p[CYI]]],
            rectify: prob.rectify,
            lo2: [lo_o, lo_i],
            hi2: [hi_o, hi_i],
            free: [[0; MAXP]; 4],
            nfree: [0; 4],
        };
        for class in 0..4 {
            let moved = |a: &usize| {
                let geometry_o = [CXO, CYO, HOLE, RIM].contains(a);
                let geometry_i = [CXI, CYI, RI, RIH].contains(a);
                (class & OUTER != 0 || !geometry_o)
                    && (class & INNER != 0 || !geometry_i)
                    && (class != 0 || *a != S)
            };
            for &a in free.iter().filter(|a| moved(a)) {
                out.free[class][out.nfree[class]] = a;
                out.nfree[class] += 1;
            }
        }
        out
    }

    /// The class of the pixel at (`fx`, `fy`).
    #[inline(always)]
    fn of(&self, fx: f64, fy: f64) -> usize {
        let active = |shape: usize| {
            let [cx, cy] = self.centre[shape];
            let [[a, b], [c, d]] = self.rectify;
            let (dx, dy) = (fx - cx, fy - cy);
            let (u, v) = (a * dx + b * dy, c * dx + d * dy);
            let d2 = u * u + v * v;
            d2 >= self.lo2[shape] && d2 <= self.hi2[shape]
        };
        (if active(0) { OUTER } else { 0 }) | (if active(1) { INNER } else { 0 })
    }
}

impl Sums {
    /// The lanes summed, the lower triangle mirrored.
    fn fold(&self) -> Normal {
        let total = |v: &Lanes| v.iter().map(|&x| x as f64).sum::<f64>();
        let mut out = Normal {
            h: [[0.0; MAXP]; MAXP],
            g: [0.0; MAXP],
            cost: self.cost.iter().sum(),
            n: self.n,
        };
        let free = &self.free[..self.nfree];
        for (i, &a) in free.iter().enumerate() {
            out.g[a] = total(&self.g[a]);
            for &b in &free[i..] {
                let v = total(&self.h[a][b]);
                (out.h[a][b], out.h[b][a]) = (v, v);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests;
