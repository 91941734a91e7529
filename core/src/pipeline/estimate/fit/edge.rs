//! The blurred circle edge, `E(d) = ½·erfc(d/(√2·s))`, and its derivative, written without
//! branches or library calls so that the model's pixel loop runs four pixels to a vector
//! (see `normal.rs`).

use std::f64::consts::{FRAC_1_SQRT_2, LN_2, LOG2_E};

/// Beyond this many blur widths an edge is flat (Φ(−4) = 3e-5 of the contrast, 0.006 DN on
/// the paper rig, against 2.5 DN of noise, and symmetric about the circle): exactly 0 or 1,
/// with no slope.
pub(super) const FLAT: f64 = 4.0;

/// 1/√(2π): the normal density's peak.
const FRAC_1_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

/// e^(−y) for 0 ≤ y ≤ 9 (FLAT²/2 = 8 is the most an edge asks), to 3e-10 relative (the
/// erfc formula it serves is good to 1.5e-7): y = n·ln 2 + r with |r| ≤ ½ ln 2, e^(−r) by
/// its Taylor series to r⁸, 2^(−n) built in the exponent bits. No table, no call: it
/// vectorises, where `f64::exp` is a libm call.
#[inline(always)]
pub(super) fn exp_neg(y: f64) -> f64 {
    // Round y·log₂e to an integer with the 1.5·2⁵² trick: the integer lands in the low
    // mantissa bits, exact for |n| < 2⁵¹.
    const ROUND: f64 = 6_755_399_441_055_744.0;
    let shifted = y * LOG2_E + ROUND;
    let n = shifted - ROUND;
    let n_bits = shifted.to_bits().wrapping_sub(ROUND.to_bits());
    // Cody–Waite: ln 2 in two parts, so r is exact to the last bits.
    const LN2_HI: f64 = 0.693_147_180_369_123_8;
    const LN2_LO: f64 = LN_2 - LN2_HI;
    let r = (y - n * LN2_HI) - n * LN2_LO;
    // e^(−r) = Σ (−r)^i / i!, Horner from the 8th term.
    let mut e = FACT_INV[8];
    for c in FACT_INV[1..8].iter().rev() {
        e = e * -r + c;
    }
    let e = e * -r + 1.0;
    // 2^(−n): the biased exponent 1023 − n.
    e * f64::from_bits((1023u64.wrapping_sub(n_bits)) << 52)
}

/// 1/i! for i = 0..8: the series' coefficients.
const FACT_INV: [f64; 9] = {
    let mut f = [1.0; 9];
    let mut i = 1;
    while i < 9 {
        f[i] = f[i - 1] / i as f64;
        i += 1;
    }
    f
};

/// ½·erfc(x) and e^(−x²) for x ≥ 0, sharing the one exponential (Abramowitz & Stegun
/// 7.1.26, absolute error < 1.5e-7: far below a DN on any contrast).
#[inline(always)]
fn half_erfc(x: f64) -> (f64, f64) {
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let g = exp_neg(x * x);
    (0.5 * poly * g, g)
}

/// Blurred edge: coverage E and its derivative dE/dd at signed distance `d`, for the blur
/// width's reciprocal `inv_s`. Branch-free: a flat edge is selected, not skipped.
#[inline(always)]
pub(super) fn edge(d: f64, inv_s: f64) -> (f64, f64) {
    let t = d * inv_s;
    let a = t.abs();
    let (h, g) = half_erfc(a.min(FLAT) * FRAC_1_SQRT_2);
    let flat = a > FLAT;
    let e = match (flat, t >= 0.0) {
        (false, true) => h,
        (false, false) => 1.0 - h,
        (true, true) => 0.0,
        (true, false) => 1.0,
    };
    // dE/dd = −φ(t)/s, and e^(−x²) with x = t/√2 is e^(−t²/2).
    let de = if flat {
        0.0
    } else {
        -g * inv_s * FRAC_1_SQRT_2PI
    };
    (e, de)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_neg_matches_the_library() {
        let mut worst = 0f64;
        for i in 0..=90_000 {
            let y = i as f64 * 1e-4;
            let want = (-y).exp();
            worst = worst.max(((exp_neg(y) - want) / want).abs());
        }
        assert!(worst < 3e-10, "worst relative error {worst:e}");
    }

    #[test]
    fn fast_edge_matches_erfc() {
        let s = 0.8;
        for i in -700..=700 {
            let d = i as f64 * 0.01;
            let (e, de) = edge(d, 1.0 / s);
            let want = 0.5 * libm::erfc(d / s * FRAC_1_SQRT_2);
            // Beyond FLAT·s the edge is cut to 0 or 1.
            let tol = if d.abs() > 3.1 { 4e-5 } else { 4e-7 };
            assert!((e - want).abs() < tol, "E({d}) = {e} vs {want}");
            let h = 1e-5;
            let num = (0.5 * libm::erfc((d + h) / s * FRAC_1_SQRT_2)
                - 0.5 * libm::erfc((d - h) / s * FRAC_1_SQRT_2))
                / (2.0 * h);
            assert!(
                (de - num).abs() < 1e-6 || d.abs() > 3.1,
                "E'({d}) = {de} vs {num}"
            );
        }
    }
}
