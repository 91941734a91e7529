//! Light that changes in time: auto-exposure gain wandering from frame to frame (a random
//! walk reflected off its bounds) and mains flicker seen through a rolling shutter (bands of
//! rows, rolling from frame to frame).
//!
//! Both are functions of (seed, frame sequence) alone, like every other per-frame effect:
//! the walk is built by midpoint displacement (Lévy's construction of Brownian motion), so
//! frame i's gain costs ~20 hashed deviates whatever i, not i steps.

use crate::camera::CameraModel;
use std::f64::consts::{PI, TAU};

/// SplitMix64 finaliser.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// A standard normal deviate keyed by `key` (Box–Muller on two hashed uniforms).
fn normal(key: u64) -> f64 {
    let a = mix(key);
    let b = mix(a ^ 0x5851_f42d_4c95_7f2d);
    let u1 = ((a >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
    let u2 = (b >> 11) as f64 / (1u64 << 53) as f64;
    (-2.0 * u1.ln()).sqrt() * (TAU * u2).cos()
}

/// Levels of the midpoint construction: one span covers 2^20 frames (9.7 h at 30 fps).
const LEVELS: u32 = 20;

/// Standard Brownian motion at integer time `i` (variance i), seeded.
pub fn brownian(seed: u64, i: u64) -> f64 {
    let span = 1u64 << LEVELS;
    // Whole spans: a plain random walk of their end points.
    let (whole, part) = (i / span, i % span);
    let mut start = 0.0;
    for k in 0..whole {
        start += (span as f64).sqrt() * normal(mix(seed ^ 0xa5a5) ^ k);
    }
    let span_seed = mix(seed ^ whole.wrapping_mul(0x9e37_79b9));
    let end = start + (span as f64).sqrt() * normal(span_seed);
    // Bisect towards `part`, drawing each midpoint given its interval's ends.
    let (mut lo, mut hi, mut b_lo, mut b_hi) = (0u64, span, start, end);
    while hi - lo > 1 && part != lo && part != hi {
        let mid = (lo + hi) / 2;
        let sd = ((hi - lo) as f64 / 4.0).sqrt();
        let b_mid = 0.5 * (b_lo + b_hi) + sd * normal(span_seed ^ mix(mid));
        if part < mid {
            (hi, b_hi) = (mid, b_mid);
        } else {
            (lo, b_lo) = (mid, b_mid);
        }
    }
    if part == lo {
        b_lo
    } else {
        b_hi
    }
}

/// Fold `x` into [lo, hi] by reflecting off the bounds (a reflected random walk).
fn reflect(x: f64, lo: f64, hi: f64) -> f64 {
    let w = hi - lo;
    if w <= 0.0 {
        return lo;
    }
    let t = (x - lo).rem_euclid(2.0 * w);
    lo + if t <= w { t } else { 2.0 * w - t }
}

/// The auto-exposure gain of frame `sequence`: 1 at frame 0, a random walk of
/// `ae_wander_rms` per frame, reflected into 1 ± `ae_gain_range`. Exactly 1 when off.
pub fn ae_gain(cam: &CameraModel, seed: u64, sequence: u64) -> f64 {
    if cam.ae_wander_rms == 0.0 {
        return 1.0;
    }
    let walk = cam.ae_wander_rms * brownian(mix(seed ^ 0x6165), sequence);
    reflect(1.0 + walk, 1.0 - cam.ae_gain_range, 1.0 + cam.ae_gain_range)
}

/// Phase (rad) of the light's modulation when frame `sequence` starts its exposure: frames
/// start every `frame_period_ms`, from a phase set by the seed.
pub fn flicker_phase(cam: &CameraModel, seed: u64, sequence: u64) -> f64 {
    let phase0 = TAU * (mix(seed ^ 0x666c) >> 11) as f64 / (1u64 << 53) as f64;
    let cycles_per_frame = (cam.flicker_hz * cam.frame_period_ms * 1e-3).fract();
    let cycles = (cycles_per_frame * (sequence % (1 << 40)) as f64).fract();
    phase0 + TAU * cycles
}

/// Relative light of row `row` of a frame whose exposure starts at modulation phase `phase`:
/// the light `1 + depth·cos(2πft + φ)` averaged over the row's exposure, which starts
/// `row·row_time_us` after the first row's. Exactly 1 without flicker bands.
pub fn row_gain(cam: &CameraModel, phase: f64, row: u32) -> f64 {
    if cam.flicker_band_depth == 0.0 {
        return 1.0;
    }
    let f = cam.flicker_hz;
    let t_exp = cam.exposure_ms * 1e-3;
    let x = PI * f * t_exp;
    let sinc = if x.abs() < 1e-12 { 1.0 } else { x.sin() / x };
    let t_mid = row as f64 * cam.row_time_us * 1e-6 + 0.5 * t_exp;
    1.0 + cam.flicker_band_depth * sinc * (TAU * f * t_mid + phase).cos()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn brownian_increments_have_unit_variance_and_are_consistent() {
        let n = 4000u64;
        let b: Vec<f64> = (0..=n).map(|i| brownian(7, i)).collect();
        assert_eq!(b[0], 0.0);
        let inc: Vec<f64> = b.windows(2).map(|w| w[1] - w[0]).collect();
        let var = inc.iter().map(|d| d * d).sum::<f64>() / n as f64;
        assert!((var - 1.0).abs() < 0.08, "step variance {var}");
        // The same frame asked again (in any order) is the same value.
        assert_eq!(brownian(7, 1234), b[1234]);
        assert_ne!(brownian(8, 1234), b[1234]);
        // Increments are uncorrelated at lag 1.
        let c = inc.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / n as f64;
        assert!(c.abs() < 0.06, "lag-1 correlation {c}");
    }

    #[test]
    fn reflect_keeps_within_bounds() {
        assert_eq!(reflect(1.07, 0.95, 1.05), 1.03);
        assert!((reflect(0.9, 0.95, 1.05) - 1.0).abs() < 1e-12);
        assert_eq!(reflect(1.01, 0.95, 1.05), 1.01);
    }
}
