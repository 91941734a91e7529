//! Give each commanded step its measured position from the interferometer trace.
//!
//! Two ways, for the two kinds of logs:
//! - [`align_by_time`]: the job knows when the axis was settled at each step (settle to frame
//!   grabbed); the readings inside that window are averaged. Needs a log with times on the
//!   same clock (up to a known offset).
//! - [`align_by_pattern`]: find the step pattern in the trace itself: plateaus where the reading
//!   stays within a tolerance, matched to the commanded steps by their spacing. Needs no clock.
//!
//! The laser measures along its beam from its own datum, and depending on the optics its sign
//! may be opposite to the axis'. Both are taken from the data: the sign from the correlation of
//! readings with commanded positions, the datum at the first step. So for step i
//! `measured_um = commanded_0 + sign * (reading_i - reading_0)` and
//! `error_um = measured_um - commanded_um` (0 at the first step by construction).

use super::{Reading, Xl80Log};
use serde::{Deserialize, Serialize};
use std::time::SystemTime;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AlignError {
    #[error("no steps to align")]
    NoSteps,
    #[error("the interferometer log has no times (or no start date); align by pattern instead")]
    NoTimes,
    #[error("found {found} plateaus in the trace, the job has {need} steps (tolerance {tol_um} µm, at least {min_samples} samples each)")]
    TooFewPlateaus {
        found: usize,
        need: usize,
        tol_um: f64,
        min_samples: usize,
    },
    #[error("the step pattern is not in the trace: best match leaves {rms_um:.1} µm RMS (limit {max_rms_um} µm)")]
    NoMatch { rms_um: f64, max_rms_um: f64 },
    #[error("the step pattern fits the trace at plateaus {first} and {second} alike ({rms_um:.2} vs {other_rms_um:.2} µm RMS): trim the log to the job, or align by time")]
    Ambiguous {
        first: usize,
        second: usize,
        rms_um: f64,
        other_rms_um: f64,
    },
}

/// When the axis was settled at one step (wall clock), and where it was told to be.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepWindow {
    pub commanded_um: f64,
    pub from: SystemTime,
    pub to: SystemTime,
}

/// One step, aligned.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepAlignment {
    pub index: usize,
    pub commanded_um: f64,
    /// Mean raw laser reading over the step (its own datum and sign).
    pub reading_um: Option<f64>,
    /// Position in the axis' frame (see the module docs).
    pub measured_um: Option<f64>,
    pub error_um: Option<f64>,
    /// Standard deviation of the readings averaged.
    pub spread_um: Option<f64>,
    pub samples: usize,
    /// First and last reading's time, seconds on the log's clock.
    pub t_s: Option<[f64; 2]>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PatternOptions {
    /// A plateau is a run of readings within this distance of the run's mean.
    pub tol_um: f64,
    /// Shorter runs are motion, not plateaus.
    pub min_samples: usize,
    /// Give up when the best match's residual RMS is larger.
    pub max_rms_um: f64,
}

impl Default for PatternOptions {
    fn default() -> Self {
        PatternOptions {
            tol_um: 5.0,
            min_samples: 3,
            max_rms_um: 20.0,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Stats {
    mean: f64,
    std: f64,
    n: usize,
    t: Option<[f64; 2]>,
}

fn stats(rs: &[Reading]) -> Option<Stats> {
    if rs.is_empty() {
        return None;
    }
    let n = rs.len();
    let mean = rs.iter().map(|r| r.position_um).sum::<f64>() / n as f64;
    let var = rs
        .iter()
        .map(|r| (r.position_um - mean).powi(2))
        .sum::<f64>()
        / n as f64;
    let t = match (rs[0].t_s, rs[n - 1].t_s) {
        (Some(a), Some(b)) => Some([a, b]),
        _ => None,
    };
    Some(Stats {
        mean,
        std: var.sqrt(),
        n,
        t,
    })
}

/// Sign of the laser against the axis: from the correlation of readings with commands.
fn sign_of(pairs: &[(f64, f64)]) -> f64 {
    let Some(&(c0, r0)) = pairs.first() else {
        return 1.0;
    };
    let s: f64 = pairs.iter().map(|(c, r)| (c - c0) * (r - r0)).sum();
    if s < 0.0 {
        -1.0
    } else {
        1.0
    }
}

fn finish(commanded: &[f64], per_step: &[Option<Stats>]) -> Vec<StepAlignment> {
    let pairs: Vec<(f64, f64)> = commanded
        .iter()
        .zip(per_step)
        .filter_map(|(c, s)| s.map(|s| (*c, s.mean)))
        .collect();
    let sign = sign_of(&pairs);
    let datum = pairs.first().copied();
    commanded
        .iter()
        .zip(per_step)
        .enumerate()
        .map(|(index, (&commanded_um, s))| {
            let measured_um = match (s, datum) {
                (Some(s), Some((c0, r0))) => Some(c0 + sign * (s.mean - r0)),
                _ => None,
            };
            StepAlignment {
                index,
                commanded_um,
                reading_um: s.map(|s| s.mean),
                measured_um,
                error_um: measured_um.map(|m| m - commanded_um),
                spread_um: s.map(|s| s.std),
                samples: s.map_or(0, |s| s.n),
                t_s: s.and_then(|s| s.t),
            }
        })
        .collect()
}

/// Average the readings inside each step's settled window. `log_minus_pc_s` is the log's
/// clock minus the PC's (0 when the XL-80 software runs on the rig PC). Steps with no reading
/// in their window get `None`s (and `samples: 0`).
pub fn align_by_time(
    log: &Xl80Log,
    steps: &[StepWindow],
    log_minus_pc_s: f64,
) -> Result<Vec<StepAlignment>, AlignError> {
    if steps.is_empty() {
        return Err(AlignError::NoSteps);
    }
    // Readings as (seconds since the epoch on the PC clock, reading).
    let timed: Vec<(f64, &Reading)> = log
        .readings
        .iter()
        .filter_map(|r| {
            let t = log.time_of(r)?;
            let s = t.duration_since(std::time::UNIX_EPOCH).ok()?.as_secs_f64();
            Some((s - log_minus_pc_s, r))
        })
        .collect();
    if timed.is_empty() {
        return Err(AlignError::NoTimes);
    }
    let epoch_s = |t: SystemTime| {
        t.duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs_f64())
            .unwrap_or(0.0)
    };
    let per_step: Vec<Option<Stats>> = steps
        .iter()
        .map(|w| {
            let (a, b) = (epoch_s(w.from), epoch_s(w.to));
            let inside: Vec<Reading> = timed
                .iter()
                .filter(|(t, _)| *t >= a && *t <= b)
                .map(|(_, r)| **r)
                .collect();
            stats(&inside)
        })
        .collect();
    let commanded: Vec<f64> = steps.iter().map(|s| s.commanded_um).collect();
    Ok(finish(&commanded, &per_step))
}

/// Runs of readings that stay within `tol_um` of their mean, at least `min_samples` long
/// (one sample trimmed from each end when there are enough, as they may be arriving/leaving).
pub fn plateaus(readings: &[Reading], opts: &PatternOptions) -> Vec<std::ops::Range<usize>> {
    let mut out = Vec::new();
    let mut start = 0;
    let mut sum = 0.0;
    let close = |start: usize, end: usize, out: &mut Vec<std::ops::Range<usize>>| {
        let n = end - start;
        if n >= opts.min_samples {
            if n >= opts.min_samples + 2 {
                out.push(start + 1..end - 1);
            } else {
                out.push(start..end);
            }
        }
    };
    for (i, r) in readings.iter().enumerate() {
        let n = (i - start) as f64;
        if n > 0.0 && (r.position_um - sum / n).abs() > opts.tol_um {
            close(start, i, &mut out);
            start = i;
            sum = 0.0;
        }
        sum += r.position_um;
    }
    close(start, readings.len(), &mut out);
    // Merge neighbours at the same level (a glitch split one plateau in two).
    let mean = |r: &std::ops::Range<usize>| {
        readings[r.clone()]
            .iter()
            .map(|x| x.position_um)
            .sum::<f64>()
            / r.len() as f64
    };
    let mut merged: Vec<std::ops::Range<usize>> = Vec::new();
    for r in out {
        match merged.last_mut() {
            Some(last) if (mean(last) - mean(&r)).abs() <= opts.tol_um => last.end = r.end,
            _ => merged.push(r),
        }
    }
    merged
}

/// Find the commanded step pattern among the trace's plateaus: the run of consecutive
/// plateaus whose spacing matches the commanded spacing best (either sign), anywhere in the
/// trace (the log may start before and end after the job). Consecutive commanded steps must
/// differ by more than `tol_um` (else they are one plateau).
pub fn align_by_pattern(
    readings: &[Reading],
    commanded_um: &[f64],
    opts: &PatternOptions,
) -> Result<Vec<StepAlignment>, AlignError> {
    let n = commanded_um.len();
    if n == 0 {
        return Err(AlignError::NoSteps);
    }
    let found = plateaus(readings, opts);
    if found.len() < n {
        return Err(AlignError::TooFewPlateaus {
            found: found.len(),
            need: n,
            tol_um: opts.tol_um,
            min_samples: opts.min_samples,
        });
    }
    let levels: Vec<Stats> = found
        .iter()
        .map(|r| stats(&readings[r.clone()]).expect("plateaus are not empty"))
        .collect();
    // Score every placement and sign by the residual RMS after removing a common offset.
    let mut scores: Vec<(f64, usize)> = Vec::new();
    for j in 0..=levels.len() - n {
        let rms = [1.0, -1.0]
            .iter()
            .map(|sign| {
                let e: Vec<f64> = (0..n)
                    .map(|i| {
                        sign * (levels[j + i].mean - levels[j].mean)
                            - (commanded_um[i] - commanded_um[0])
                    })
                    .collect();
                let m = e.iter().sum::<f64>() / n as f64;
                (e.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n as f64).sqrt()
            })
            .fold(f64::INFINITY, f64::min);
        scores.push((rms, j));
    }
    scores.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (rms, j) = scores[0];
    if rms > opts.max_rms_um {
        return Err(AlignError::NoMatch {
            rms_um: rms,
            max_rms_um: opts.max_rms_um,
        });
    }
    // Uniform steps with extra plateaus at the same spacing (the log runs on before or after
    // the job) fit in more than one place: refuse rather than guess.
    if let Some(&(other, k)) = scores.get(1) {
        if other <= rms + opts.tol_um / 2.0 {
            return Err(AlignError::Ambiguous {
                first: j,
                second: k,
                rms_um: rms,
                other_rms_um: other,
            });
        }
    }
    let per_step: Vec<Option<Stats>> = levels[j..j + n].iter().map(|s| Some(*s)).collect();
    Ok(finish(commanded_um, &per_step))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A trace: `lead` samples at `start`, then for each target a 4-sample ramp and a
    /// plateau of `hold` samples with +-noise.
    fn trace(start: f64, targets: &[f64], hold: usize, sign: f64) -> Vec<Reading> {
        let mut v = Vec::new();
        let mut at = start;
        let push = |v: &mut Vec<Reading>, x: f64| {
            let i = v.len();
            let noise = [0.3, -0.2, 0.1, -0.3, 0.2][i % 5];
            v.push(Reading {
                t_s: Some(i as f64 * 0.01),
                position_um: 1000.0 + sign * x + noise,
                line: i,
            })
        };
        for _ in 0..10 {
            push(&mut v, at);
        }
        for &t in targets {
            for k in 1..=4 {
                push(&mut v, at + (t - at) * k as f64 / 5.0);
            }
            at = t;
            for _ in 0..hold {
                push(&mut v, at);
            }
        }
        v
    }

    #[test]
    fn finds_the_steps_and_their_errors() {
        // Reached positions differ from commanded by a few µm.
        let commanded: Vec<f64> = (0..6).map(|i| i as f64 * 100.0).collect();
        let reached: Vec<f64> = commanded
            .iter()
            .zip([0.0, 2.0, -1.5, 3.0, -2.0, 1.0])
            .map(|(c, e)| c + e)
            .collect();
        for sign in [1.0, -1.0] {
            // The axis comes from -300 µm to the job's first step.
            let r = trace(-300.0, &reached, 20, sign);
            let a = align_by_pattern(&r, &commanded, &PatternOptions::default()).unwrap();
            assert_eq!(a.len(), 6);
            assert_eq!(a[0].samples, 18, "the lead at -300 µm is not a step");
            for (s, want) in a.iter().zip([0.0, 2.0, -1.5, 3.0, -2.0, 1.0]) {
                let e = s.error_um.unwrap();
                assert!(
                    (e - want).abs() < 0.3,
                    "sign {sign} step {}: {e} vs {want}",
                    s.index
                );
                assert!(s.samples >= if s.index == 0 { 8 } else { 18 }, "{s:?}");
            }
        }
    }

    #[test]
    fn pattern_not_in_trace() {
        let r = trace(0.0, &[100.0, 200.0, 300.0], 20, 1.0);
        let e = align_by_pattern(&r, &[0.0, 500.0, 520.0], &PatternOptions::default()).unwrap_err();
        assert!(matches!(e, AlignError::NoMatch { .. }), "{e}");
        let e = align_by_pattern(
            &r,
            &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
            &PatternOptions::default(),
        )
        .unwrap_err();
        assert!(
            matches!(
                e,
                AlignError::TooFewPlateaus {
                    found: 4,
                    need: 6,
                    ..
                }
            ),
            "{e}"
        );
        // Lead at 0 then 100, 200, 300: two uniform steps fit at 0 and at 100.
        let e = align_by_pattern(&r, &[0.0, 100.0, 200.0], &PatternOptions::default()).unwrap_err();
        assert!(matches!(e, AlignError::Ambiguous { .. }), "{e}");
    }

    #[test]
    fn by_time_averages_the_window() {
        let t0 = std::time::UNIX_EPOCH + std::time::Duration::from_secs(1_000_000);
        let mut log = Xl80Log::new(super::super::Xl80Format::Csv);
        log.start = Some(t0);
        log.readings = trace(0.0, &[50.0, 100.0], 20, 1.0);
        // Lead 10 samples (0..0.1 s), ramp 4, hold 20 (0.14..0.34 s), ramp 4, hold 20.
        let at = |s: f64| t0 + std::time::Duration::from_secs_f64(s);
        let steps = [
            StepWindow {
                commanded_um: 0.0,
                from: at(0.0),
                to: at(0.095),
            },
            StepWindow {
                commanded_um: 50.0,
                from: at(0.145),
                to: at(0.335),
            },
            StepWindow {
                commanded_um: 100.0,
                from: at(0.385),
                to: at(0.575),
            },
            StepWindow {
                commanded_um: 150.0,
                from: at(9.0),
                to: at(9.5),
            },
        ];
        let a = align_by_time(&log, &steps, 0.0).unwrap();
        assert_eq!(a[0].samples, 10);
        assert_eq!(a[1].samples, 19);
        assert!(a[1].error_um.unwrap().abs() < 0.3);
        assert!(a[2].error_um.unwrap().abs() < 0.3);
        assert_eq!(a[3].samples, 0);
        assert_eq!(a[3].measured_um, None);
        // A clock offset moves the windows: 0.24 s later on the log's clock puts step 1 on step 2's plateau.
        let a = align_by_time(&log, &steps, 0.24).unwrap();
        assert!(
            (a[1].reading_um.unwrap() - 1100.0).abs() < 1.0,
            "{:?}",
            a[1]
        );
        log.start = None;
        assert_eq!(
            align_by_time(&log, &steps, 0.0).unwrap_err(),
            AlignError::NoTimes
        );
    }
}
