//! The blurred circle edge, `E(d) = ½·erfc(d/(√2·s))`, and its derivative, written without
//! branches or library calls so that the model's pixel loop runs eight pixels to a vector
//! (see `normal.rs`). Generic over the float type: the fit evaluates its pixels in `f32`,
//! the tests' reference in `f64`.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// Beyond this many blur widths an edge is flat (Φ(−4) = 3e-5 of the contrast, 0.006 DN on
/// the paper rig, against 2.5 DN of noise, and symmetric about the circle): exactly 0 or 1,
/// with no slope.
pub(super) const FLAT: f64 = 4.0;

/// 1/√(2π): the normal density's peak.
const FRAC_1_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

/// The float type a pixel is evaluated in: the operations the model needs, each one a
/// vector instruction.
pub(super) trait Real:
    Copy
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    fn c(v: f64) -> Self;
    fn sqrt(self) -> Self;
    fn abs(self) -> Self;
    fn min(self, o: Self) -> Self;
    fn max(self, o: Self) -> Self;
    /// e^(−self) for 0 ≤ self ≤ 9 (FLAT²/2 = 8 is the most an edge asks), to the type's
    /// precision: self = n·ln 2 + r with |r| ≤ ½ ln 2, e^(−r) by its Taylor series, 2^(−n)
    /// built in the exponent bits. No table, no call: it vectorises, where `exp` is a libm
    /// call.
    fn exp_neg(self) -> Self;
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

/// The methods both widths take from std as they are.
macro_rules! forward_to_std {
    ($t:ident) => {
        #[inline(always)]
        fn c(v: f64) -> $t {
            v as $t
        }
        #[inline(always)]
        fn sqrt(self) -> $t {
            $t::sqrt(self)
        }
        #[inline(always)]
        fn abs(self) -> $t {
            $t::abs(self)
        }
        #[inline(always)]
        fn min(self, o: $t) -> $t {
            $t::min(self, o)
        }
        #[inline(always)]
        fn max(self, o: $t) -> $t {
            $t::max(self, o)
        }
    };
}

impl Real for f64 {
    forward_to_std!(f64);
    /// To 3e-10 relative (the erfc formula it serves is good to 1.5e-7).
    #[inline(always)]
    fn exp_neg(self) -> f64 {
        use std::f64::consts::{LN_2, LOG2_E};
        // Round y·log₂e to an integer with the 1.5·2⁵² trick: the integer lands in the low
        // mantissa bits, exact for |n| < 2⁵¹.
        const ROUND: f64 = 6_755_399_441_055_744.0;
        let shifted = self * LOG2_E + ROUND;
        let n = shifted - ROUND;
        let n_bits = shifted.to_bits().wrapping_sub(ROUND.to_bits());
        // Cody–Waite: ln 2 in two parts, so r is exact to the last bits.
        const LN2_HI: f64 = 0.693_147_180_369_123_8;
        const LN2_LO: f64 = LN_2 - LN2_HI;
        let r = (self - n * LN2_HI) - n * LN2_LO;
        // e^(−r) = Σ (−r)^i / i!, Horner from the 8th term.
        let mut e = FACT_INV[8];
        for c in FACT_INV[1..8].iter().rev() {
            e = e * -r + c;
        }
        let e = e * -r + 1.0;
        // 2^(−n): the biased exponent 1023 − n.
        e * f64::from_bits((1023u64.wrapping_sub(n_bits)) << 52)
    }
}

impl Real for f32 {
    forward_to_std!(f32);
    /// To 2e-7 relative (two f32 roundings).
    #[inline(always)]
    fn exp_neg(self) -> f32 {
        use std::f32::consts::{LN_2, LOG2_E};
        // The 1.5·2²³ trick: exact for |n| < 2²².
        const ROUND: f32 = 12_582_912.0;
        let shifted = self * LOG2_E + ROUND;
        let n = shifted - ROUND;
        let n_bits = shifted.to_bits().wrapping_sub(ROUND.to_bits());
        // ln 2 with its low 12 mantissa bits cleared, so that n·LN2_HI is exact.
        const LN2_HI: f32 = f32::from_bits(0x3f31_7200); // 0.693145751953125
        const LN2_LO: f32 = LN_2 - LN2_HI;
        let r = (self - n * LN2_HI) - n * LN2_LO;
        // |r| ≤ 0.35: the series to r⁷ leaves 5e-9.
        let mut e = FACT_INV[7] as f32;
        for c in FACT_INV[1..7].iter().rev() {
            e = e * -r + *c as f32;
        }
        let e = e * -r + 1.0;
        e * f32::from_bits((127u32.wrapping_sub(n_bits)) << 23)
    }
}

/// ½·erfc(x) and e^(−x²) for x ≥ 0, sharing the one exponential (Abramowitz & Stegun
/// 7.1.26, absolute error < 1.5e-7: far below a DN on any contrast).
#[inline(always)]
fn half_erfc<T: Real>(x: T) -> (T, T) {
    let c = T::c;
    let t = c(1.0) / (c(1.0) + c(0.327_591_1) * x);
    let poly = t
        * (c(0.254_829_592)
            + t * (c(-0.284_496_736)
                + t * (c(1.421_413_741) + t * (c(-1.453_152_027) + t * c(1.061_405_429)))));
    let g = (x * x).exp_neg();
    (c(0.5) * poly * g, g)
}

/// Blurred edge: coverage E and its derivative dE/dd at signed distance `d`, for the blur
/// width's reciprocal `inv_s`. Branch-free: a flat edge is selected, not skipped.
#[inline(always)]
pub(super) fn edge<T: Real>(d: T, inv_s: T) -> (T, T) {
    let c = T::c;
    let t = d * inv_s;
    let a = t.abs();
    let (h, g) = half_erfc(a.min(c(FLAT)) * c(std::f64::consts::FRAC_1_SQRT_2));
    let flat = a > c(FLAT);
    let e = match (flat, t >= c(0.0)) {
        (false, true) => h,
        (false, false) => c(1.0) - h,
        (true, true) => c(0.0),
        (true, false) => c(1.0),
    };
    // dE/dd = −φ(t)/s, and e^(−x²) with x = t/√2 is e^(−t²/2).
    let de = if flat {
        c(0.0)
    } else {
        -g * inv_s * c(FRAC_1_SQRT_2PI)
    };
    (e, de)
}

/// [`edge`] where it is known flat (|d| > FLAT·s): the coverage selected by the side, no
/// slope; the same values [`edge`] gives there, without the special functions.
#[inline(always)]
pub(super) fn flat_edge<T: Real>(d: T) -> (T, T) {
    let c = T::c;
    (if d >= c(0.0) { c(0.0) } else { c(1.0) }, c(0.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_1_SQRT_2;

    #[test]
    fn exp_neg_matches_the_library() {
        let mut worst = 0f64;
        for i in 0..=90_000 {
            let y = i as f64 * 1e-4;
            let want = (-y).exp();
            worst = worst.max(((y.exp_neg() - want) / want).abs());
        }
        assert!(worst < 3e-10, "worst relative error {worst:e}");
        let mut worst = 0f64;
        for i in 0..=90_000 {
            let y = i as f32 * 1e-4;
            let want = (-(y as f64)).exp();
            worst = worst.max(((y.exp_neg() as f64 - want) / want).abs());
        }
        // Measured: 9.4e-8, about one f32 rounding.
        assert!(worst < 2e-7, "f32: worst relative error {worst:e}");
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
            // The f32 edge the fit evaluates: A&S's 1.5e-7 plus a few roundings.
            let (e32, de32) = edge(d as f32, (1.0 / s) as f32);
            assert!((e32 as f64 - e).abs() < 5e-7, "f32 E({d}) = {e32} vs {e}");
            assert!(
                (de32 as f64 - de).abs() < 5e-7,
                "f32 E'({d}) = {de32} vs {de}"
            );
        }
    }
}
