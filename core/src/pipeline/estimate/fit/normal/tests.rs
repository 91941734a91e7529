//! The batched normal equations against the per-pixel form they replaced, on a synthetic
//! target: the same sums to f32 rounding, and the AVX2 build the same bits as the portable one.

use super::super::edge::edge;
use super::super::{
    Problem, Window, B0, BX, BY, C, CI, CXI, CXO, CYI, CYO, HOLE, MAXP, NC, RI, RIH, RIM, S,
};
use super::Normal;
use crate::pipeline::plane::Plane;

/// The per-pixel form the batched one replaced: the dense row, its zeros skipped.
fn reference(prob: &Problem, p: &[f64; MAXP]) -> Normal {
    let mut out = Normal {
        h: [[0.0; MAXP]; MAXP],
        g: [0.0; MAXP],
        cost: 0.0,
        n: 0,
    };
    let ring_inner = prob.np == MAXP;
    let s = p[S];
    let reach2 = prob.win.reach * prob.win.reach;
    for y in (prob.win.y0..prob.win.y1).step_by(prob.step) {
        let fy = y as f64;
        let row = &prob.plane.data[y * prob.plane.width..(y + 1) * prob.plane.width];
        let xs = row
            .iter()
            .enumerate()
            .take(prob.win.x1)
            .skip(prob.win.x0)
            .step_by(prob.step);
        for (x, &v) in xs {
            let fx = x as f64;
            let (rx, ry) = (fx - prob.reach_centre[0], fy - prob.reach_centre[1]);
            if rx * rx + ry * ry > reach2 {
                continue;
            }
            // The distance in the rectified frame, its centre derivatives by differences.
            let m = prob.rectify;
            let rho = |dx: f64, dy: f64| {
                (m[0][0] * dx + m[0][1] * dy)
                    .hypot(m[1][0] * dx + m[1][1] * dy)
                    .max(1e-9)
            };
            let d_rho = |dx: f64, dy: f64| {
                let h = 1e-6;
                [
                    (rho(dx - h, dy) - rho(dx + h, dy)) / (2.0 * h),
                    (rho(dx, dy - h) - rho(dx, dy + h)) / (2.0 * h),
                ]
            };
            let (dxo, dyo) = (fx - p[CXO], fy - p[CYO]);
            let ro = rho(dxo, dyo);
            let (dxi, dyi) = (fx - p[CXI], fy - p[CYI]);
            let ri = rho(dxi, dyi);
            let (e_rim, d_rim) = edge(ro - p[RIM], 1.0 / s);
            let (e_hole, d_hole) = edge(ro - p[HOLE], 1.0 / s);
            let (e_in, d_in) = edge(ri - p[RI], 1.0 / s);
            let (e_ih, d_ih) = if ring_inner {
                edge(ri - p[RIH], 1.0 / s)
            } else {
                (0.0, 0.0)
            };
            let (cov_o, cov_i) = (e_rim - e_hole, e_in - e_ih);
            let (bx, by) = (
                (fx - prob.mid[0]) * prob.inv_half,
                (fy - prob.mid[1]) * prob.inv_half,
            );
            let l = p[B0] + p[BX] * bx + p[BY] * by;
            let mono = [1.0, bx, by];
            let poly =
                |at: usize| -> f64 { mono.iter().zip(&p[at..at + NC]).map(|(m, q)| m * q).sum() };
            let (c_o, c_i) = (poly(C), poly(CI));
            let shade = 1.0 - c_o * cov_o - c_i * cov_i;
            let r = v as f64 - l * shade;
            out.cost += r * r;
            out.n += 1;
            // The Jacobian row: the background terms always, the contrast inside the
            // shapes, the geometry only near an edge (zero elsewhere).
            let mut j = [0f64; MAXP];
            j[B0] = shade;
            j[BX] = bx * shade;
            j[BY] = by * shade;
            let terms = if prob.planes { NC } else { 1 };
            for (at, cov) in [(C, cov_o), (CI, cov_i)] {
                if cov != 0.0 {
                    for (jc, m) in j[at..at + terms].iter_mut().zip(&mono) {
                        *jc = -l * cov * m;
                    }
                }
            }
            let (lco, lci) = (-l * c_o, -l * c_i);
            let douter = d_rim - d_hole;
            if douter != 0.0 {
                let [gx, gy] = d_rho(dxo, dyo);
                j[CXO] = lco * douter * gx;
                j[CYO] = lco * douter * gy;
                j[RIM] = lco * -d_rim;
                j[HOLE] = lco * d_hole;
            }
            let dinner = d_in - d_ih;
            if dinner != 0.0 {
                let [gx, gy] = d_rho(dxi, dyi);
                j[CXI] = lci * dinner * gx;
                j[CYI] = lci * dinner * gy;
                j[RI] = lci * -d_in;
                j[RIH] = lci * d_ih;
            }
            if douter != 0.0 || dinner != 0.0 {
                // dE/ds = −E'(d)·d/s.
                let ds_o = -(d_rim * (ro - p[RIM]) - d_hole * (ro - p[HOLE])) / s;
                let ds_i =
                    -(d_in * (ri - p[RI]) - d_ih * if ring_inner { ri - p[RIH] } else { 0.0 }) / s;
                j[S] = lco * ds_o + lci * ds_i;
            }
            // Jᵀr and JᵀJ from the dense row: fixed-size loops the compiler vectorises,
            // skipping the row's zeros (most pixels touch only the background terms).
            for (a, &va) in j.iter().enumerate() {
                if va == 0.0 {
                    continue;
                }
                out.g[a] += va * r;
                for (h, &vb) in out.h[a].iter_mut().zip(&j) {
                    *h += va * vb;
                }
            }
        }
    }
    out
}

/// A 61x61 ring around an inner shape (a disk, or a ring when `ring_inner`), soft edges,
/// an uneven light and a little deterministic noise.
fn plane() -> Plane {
    let (w, h) = (61, 61);
    let mut data = Vec::with_capacity(w * h);
    let mut seed = 12345u64;
    for y in 0..h {
        for x in 0..w {
            let (dx, dy) = (x as f64 - 30.3, y as f64 - 29.6);
            let r = (dx * dx + dy * dy).sqrt();
            let soft = |d: f64| 1.0 / (1.0 + (d / 0.7).exp());
            let ink = soft(r - 22.0) - soft(r - 16.0) + soft(r - 8.0);
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let noise = ((seed >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 3.0;
            data.push((200.0 + 0.3 * x as f64) * (1.0 - 0.7 * ink) as f32 as f64 + noise);
        }
    }
    Plane {
        width: w,
        height: h,
        data: data.into_iter().map(|v| v as f32).collect(),
    }
}

fn params(ring_inner: bool) -> [f64; MAXP] {
    let mut p = [0.0; MAXP];
    (p[CXO], p[CYO], p[HOLE], p[RIM]) = (30.1, 29.8, 16.2, 21.9);
    (p[CXI], p[CYI], p[RI], p[S]) = (30.5, 29.5, 8.1, 0.9);
    (p[B0], p[BX], p[BY]) = (205.0, 8.0, -1.0);
    (p[C], p[C + 1], p[C + 2]) = (0.7, 0.01, -0.02);
    (p[CI], p[CI + 1], p[CI + 2]) = (0.68, -0.015, 0.005);
    p[RIH] = if ring_inner { 3.0 } else { 0.0 };
    p
}

fn problem<'a>(
    plane: &'a Plane,
    win: &'a Window,
    ring_inner: bool,
    planes: bool,
    step: usize,
) -> Problem<'a> {
    Problem {
        plane,
        win,
        np: if ring_inner { MAXP } else { MAXP - 1 },
        step,
        mid: [30.0, 30.0],
        inv_half: 1.0 / 30.0,
        reach_centre: [30.0, 30.0],
        planes,
        rectify: [[1.0, 0.0], [0.0, 1.0]],
    }
}

/// A window inside the plane whose reach leaves some pixels out.
fn inner_window() -> Window {
    Window {
        x0: 1,
        y0: 2,
        x1: 60,
        y1: 59,
        reach: 27.5,
    }
}

#[test]
fn batched_sums_equal_the_per_pixel_ones() {
    let (plane, win) = (plane(), inner_window());
    // The last three measure the shapes as ellipses 3 % out of round (`rectify`), the last
    // turned too (a map that is not symmetric: a board turned in the image).
    let ellipse = [[1.012, 0.008], [0.008, 0.988]];
    let (sn, cs) = 0.3f64.sin_cos();
    let turned = [
        [cs * 1.012 - sn * 0.008, cs * 0.008 - sn * 0.988],
        [sn * 1.012 + cs * 0.008, sn * 0.008 + cs * 0.988],
    ];
    for (ring_inner, planes, step, rectify) in [
        (false, false, 1, None),
        (false, true, 1, None),
        (true, true, 2, None),
        (true, false, 3, None),
        (false, true, 1, Some(ellipse)),
        (true, false, 2, Some(ellipse)),
        (true, true, 1, Some(turned)),
    ] {
        let mut prob = problem(&plane, &win, ring_inner, planes, step);
        prob.rectify = rectify.unwrap_or(prob.rectify);
        // The blur of the params (0.9 px); one so sharp that most pixels are flat (no
        // edge's special functions); one so wide that every pixel sees both shapes' edges.
        for s in [None, Some(0.5), Some(4.0)] {
            let mut p = params(ring_inner);
            if let Some(s) = s {
                p[S] = s;
            }
            let case = format!(
                "ring_inner {ring_inner}, planes {planes}, step {step}, s {}, rectify {rectify:?}",
                p[S]
            );
            assert_same_sums(&prob, &p, &case);
        }
    }
}

/// The batched sums of `prob` at `p` against the per-pixel reference.
fn assert_same_sums(prob: &Problem, p: &[f64; MAXP], case: &str) {
    let (planes, step) = (prob.planes, prob.step);
    let (got, want) = (prob.normal(p), reference(prob, p));
    assert_eq!(got.n, want.n, "{case}");
    // Some pixels are left out (outside the reach), so no batch is always full.
    assert!(got.n % 8 != 0 || step > 1, "{case}: {} pixels", got.n);
    // The lanes sum in f32 (measured worst 1.5e-6 of the scale); the reference in f64.
    let close = |a: f64, b: f64, scale: f64| (a - b).abs() <= 3e-6 * scale.max(1.0);
    assert!(
        close(got.cost, want.cost, want.cost),
        "{case}: cost {} vs {}",
        got.cost,
        want.cost
    );
    for a in 0..prob.np {
        let ga = want.h[a][a].sqrt() * want.cost.sqrt();
        assert!(
            close(got.g[a], want.g[a], ga),
            "{case}: g[{a}] {} vs {}",
            got.g[a],
            want.g[a]
        );
        for b in 0..prob.np {
            let hab = (want.h[a][a] * want.h[b][b]).sqrt();
            assert!(
                close(got.h[a][b], want.h[a][b], hab),
                "{case}: h[{a}][{b}] {} vs {}",
                got.h[a][b],
                want.h[a][b]
            );
        }
    }
    // The held gradients stay out of the sums, as the per-pixel form left them.
    if !planes {
        for a in [C + 1, C + 2, CI + 1, CI + 2] {
            assert_eq!(got.h[a][a], 0.0, "{case}");
            assert_eq!(got.g[a], 0.0, "{case}");
        }
    }
}

#[test]
fn the_dispatched_build_gives_the_portable_bits() {
    let plane = plane();
    let win = Window {
        x0: 0,
        y0: 0,
        x1: 61,
        y1: 61,
        reach: 28.0,
    };
    let prob = problem(&plane, &win, true, true, 1);
    let p = params(true);
    let (a, b) = (prob.normal(&p), prob.normal_lanes(&p));
    assert_eq!(a.cost.to_bits(), b.cost.to_bits());
    for i in 0..MAXP {
        assert_eq!(a.g[i].to_bits(), b.g[i].to_bits(), "g[{i}]");
        for k in 0..MAXP {
            assert_eq!(a.h[i][k].to_bits(), b.h[i][k].to_bits(), "h[{i}][{k}]");
        }
    }
}

/// A pass with the contrast gradients free, their rows held, is the even-ink model's own
/// pass to the bit (the fit reads the score test off such a pass: `solve`'s `wide`).
#[test]
fn a_wide_pass_held_is_the_even_pass() {
    let (plane, win) = (plane(), inner_window());
    for ring_inner in [false, true] {
        let (even, wide) = (
            problem(&plane, &win, ring_inner, false, 1),
            problem(&plane, &win, ring_inner, true, 1),
        );
        let mut p = params(ring_inner);
        // The gradients where the even-ink model holds them.
        for a in [C + 1, C + 2, CI + 1, CI + 2] {
            p[a] = 0.0;
        }
        let (a, b) = (even.normal(&p), wide.normal(&p).held());
        assert_eq!(
            a.cost.to_bits(),
            b.cost.to_bits(),
            "ring_inner {ring_inner}"
        );
        assert_eq!(a.n, b.n);
        for i in 0..MAXP {
            assert_eq!(a.g[i].to_bits(), b.g[i].to_bits(), "g[{i}]");
            for k in 0..MAXP {
                assert_eq!(a.h[i][k].to_bits(), b.h[i][k].to_bits(), "h[{i}][{k}]");
            }
        }
        // And the wide pass has the gradients' sums the held one dropped.
        assert!(wide.normal(&p).h[C + 1][C + 1] > 0.0);
    }
}
