//! Axis kinematics in real time: where the carriage truly is at any instant.
//!
//! One `Axis` is shared (behind an `Arc`) by whoever commands it (the GRBL or GCS emulator,
//! or an in-process stage) and whoever observes it (the camera's frame clock, the XL-80
//! synthesizer). Moves follow a trapezoidal velocity profile with finite speed and
//! acceleration, and end at the commanded position plus a random positioning error, as a
//! real axis does (the paper's axis was good to about 2 µm). A move runs at the axis' top
//! speed, or at a slower speed of its own (a G-code feed rate), always with the axis'
//! acceleration.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Anything that knows where the camera's line of sight truly is at an instant, in µm of
/// board travel along x and y.
pub trait TruePosition: Send + Sync {
    fn true_position_um(&self, t: Instant) -> [f64; 2];
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AxisParams {
    pub max_speed_um_s: f64,
    pub accel_um_s2: f64,
    /// RMS of the random error between commanded and reached position.
    pub position_error_rms_um: f64,
    /// Hard travel limits: a move past them trips the limit switch.
    pub hard_min_um: f64,
    pub hard_max_um: f64,
    pub seed: u64,
}

impl Default for AxisParams {
    fn default() -> Self {
        AxisParams {
            max_speed_um_s: 20_000.0,
            accel_um_s2: 500_000.0,
            position_error_rms_um: 2.0,
            hard_min_um: -5_000.0,
            hard_max_um: 300_000.0,
            seed: 1,
        }
    }
}

/// A leadscrew's periodic error: the carriage is where the screw's angle puts it, off by
/// `error_um·sin(2π·x/pitch + phase)` at nominal position x (a bent or eccentric screw, a
/// wobbling nut). The controller does not see it; the camera and the interferometer do.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Leadscrew {
    /// Amplitude of the periodic error, µm (0: none).
    pub error_um: f64,
    /// The screw's pitch (the error's period), mm.
    pub pitch_mm: f64,
    /// Phase at position 0, degrees.
    pub phase_deg: f64,
}

impl Default for Leadscrew {
    fn default() -> Self {
        Leadscrew {
            error_um: 0.0,
            pitch_mm: 5.0,
            phase_deg: 0.0,
        }
    }
}

impl Leadscrew {
    /// The realistic screw of the `webcam` rig: 2 µm on a 5 mm pitch.
    pub fn webcam() -> Leadscrew {
        Leadscrew {
            error_um: 2.0,
            ..Leadscrew::default()
        }
    }

    /// The error at nominal position `x_um`, µm (exactly 0 without one).
    pub fn error_at_um(&self, x_um: f64) -> f64 {
        if self.error_um == 0.0 {
            return 0.0;
        }
        let turns = x_um / (self.pitch_mm * 1000.0);
        self.error_um * (std::f64::consts::TAU * turns + self.phase_deg.to_radians()).sin()
    }

    /// The true position of a carriage at nominal position `x_um`.
    pub fn true_um(&self, x_um: f64) -> f64 {
        if self.error_um == 0.0 {
            x_um
        } else {
            x_um + self.error_at_um(x_um)
        }
    }
}

/// A trapezoidal move from `from_um` to `to_um`, independent of any clock: position as a
/// function of the seconds since the move began. The real-time `Axis` and `sim-session`'s
/// virtual clock both plan with it.
#[derive(Debug, Clone, Copy)]
pub struct Profile {
    pub from_um: f64,
    pub to_um: f64,
    /// Time to accelerate to `v_peak`, and time at `v_peak`.
    t_acc: f64,
    t_flat: f64,
    v_peak: f64,
    accel: f64,
}

impl Profile {
    /// A move at the axis' top speed.
    pub fn plan(from_um: f64, to_um: f64, p: &AxisParams) -> Profile {
        Profile::plan_at(from_um, to_um, p, p.max_speed_um_s)
    }

    /// A move cruising at `speed_um_s`, clamped to the axis' top speed (as GRBL clamps a
    /// feed rate to its max rate); a speed that is not a positive number means the top
    /// speed. Acceleration is the axis' own.
    pub fn plan_at(from_um: f64, to_um: f64, p: &AxisParams, speed_um_s: f64) -> Profile {
        let dist = (to_um - from_um).abs();
        let a = p.accel_um_s2;
        let cruise_um_s = if speed_um_s > 0.0 {
            speed_um_s.min(p.max_speed_um_s)
        } else {
            p.max_speed_um_s
        };
        // Triangle profile if the move is too short to reach the cruise speed.
        let v_peak = cruise_um_s.min((dist * a).sqrt());
        let t_acc = if a > 0.0 { v_peak / a } else { 0.0 };
        let d_acc = 0.5 * a * t_acc * t_acc;
        let t_flat = if v_peak > 0.0 {
            (dist - 2.0 * d_acc).max(0.0) / v_peak
        } else {
            0.0
        };
        Profile {
            from_um,
            to_um,
            t_acc,
            t_flat,
            v_peak,
            accel: a,
        }
    }

    pub fn duration_s(&self) -> f64 {
        2.0 * self.t_acc + self.t_flat
    }

    /// The highest speed the move reaches: its cruise speed, or less on a short move.
    pub fn peak_speed_um_s(&self) -> f64 {
        self.v_peak
    }

    /// Speed `s` seconds after the move began (0 before and after it).
    pub fn speed_after(&self, s: f64) -> f64 {
        let (ta, tf, v, a) = (self.t_acc, self.t_flat, self.v_peak, self.accel);
        if s <= 0.0 || s >= 2.0 * ta + tf {
            0.0
        } else if s <= ta {
            a * s
        } else if s <= ta + tf {
            v
        } else {
            v - a * (s - ta - tf)
        }
    }

    /// Position `s` seconds after the move began (clamped to the ends).
    pub fn position_after(&self, s: f64) -> f64 {
        let s = s.max(0.0);
        let dir = (self.to_um - self.from_um).signum();
        let (ta, tf, v, a) = (self.t_acc, self.t_flat, self.v_peak, self.accel);
        let d = if s <= ta {
            0.5 * a * s * s
        } else if s <= ta + tf {
            0.5 * a * ta * ta + v * (s - ta)
        } else if s <= 2.0 * ta + tf {
            let r = s - ta - tf;
            0.5 * a * ta * ta + v * tf + v * r - 0.5 * a * r * r
        } else {
            return self.to_um;
        };
        self.from_um + dir * d
    }
}

/// One planned move in real time: a profile started at `start`.
#[derive(Debug, Clone, Copy)]
struct Segment {
    start: Instant,
    profile: Profile,
}

impl Segment {
    fn duration(&self) -> Duration {
        Duration::from_secs_f64(self.profile.duration_s())
    }

    fn position_at(&self, t: Instant) -> f64 {
        self.profile
            .position_after(t.saturating_duration_since(self.start).as_secs_f64())
    }
}

struct State {
    segment: Option<Segment>,
    /// Where the axis rests when no segment is active (true position).
    rest_um: f64,
    /// The last commanded target (what the controller believes).
    commanded_um: f64,
    rng: ChaCha8Rng,
}

/// A simulated linear axis.
pub struct Axis {
    params: AxisParams,
    leadscrew: Leadscrew,
    state: Mutex<State>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MotionError {
    #[error("target {target_um} µm is past the hard limit [{min_um}, {max_um}] µm")]
    HardLimit {
        target_um: f64,
        min_um: f64,
        max_um: f64,
    },
}

impl Axis {
    pub fn new(params: AxisParams) -> Axis {
        let rng = ChaCha8Rng::seed_from_u64(params.seed);
        Axis {
            params,
            leadscrew: Leadscrew::default(),
            state: Mutex::new(State {
                segment: None,
                rest_um: 0.0,
                commanded_um: 0.0,
                rng,
            }),
        }
    }

    pub fn params(&self) -> &AxisParams {
        &self.params
    }

    /// The axis driven by a leadscrew with a periodic error (`position_at` carries it).
    pub fn with_leadscrew(mut self, leadscrew: Leadscrew) -> Axis {
        self.leadscrew = leadscrew;
        self
    }

    pub fn leadscrew(&self) -> &Leadscrew {
        &self.leadscrew
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panicking observer must not wedge the axis: the state is plain data.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Start a move to `target_um` now at the axis' top speed; returns how long it will
    /// take. A move past the hard limits is refused (the emulators turn that into their
    /// controller's alarm).
    pub fn command_move(&self, target_um: f64) -> Result<Duration, MotionError> {
        self.command_move_at(target_um, self.params.max_speed_um_s)
    }

    /// [`Axis::command_move`] cruising at `speed_um_s` (clamped to the top speed, see
    /// [`Profile::plan_at`]).
    pub fn command_move_at(
        &self,
        target_um: f64,
        speed_um_s: f64,
    ) -> Result<Duration, MotionError> {
        let p = &self.params;
        if !(p.hard_min_um..=p.hard_max_um).contains(&target_um) {
            return Err(MotionError::HardLimit {
                target_um,
                min_um: p.hard_min_um,
                max_um: p.hard_max_um,
            });
        }
        let now = Instant::now();
        let mut st = self.lock();
        let from = Self::position_locked(&st, now);
        let err = if p.position_error_rms_um > 0.0 {
            Normal::new(0.0, p.position_error_rms_um)
                .expect("finite rms")
                .sample(&mut st.rng)
        } else {
            0.0
        };
        let seg = Segment {
            start: now,
            profile: Profile::plan_at(from, target_um + err, p, speed_um_s),
        };
        st.rest_um = seg.profile.to_um;
        st.commanded_um = target_um;
        st.segment = Some(seg);
        Ok(seg.duration())
    }

    /// Stop where the axis is now (an idealised instant halt). The controller's idea of the
    /// position becomes the true one, as after a feed hold and reset.
    pub fn stop(&self) {
        let now = Instant::now();
        let mut st = self.lock();
        let here = Self::position_locked(&st, now);
        st.segment = None;
        st.rest_um = here;
        st.commanded_um = here;
    }

    /// Brake to rest at the axis' acceleration (a feed hold): the rest of the move is
    /// dropped. Returns how long the braking takes.
    pub fn brake(&self) -> Duration {
        let now = Instant::now();
        let mut st = self.lock();
        let Some(seg) = st.segment else {
            return Duration::ZERO;
        };
        let s = now.saturating_duration_since(seg.start).as_secs_f64();
        let (v, a) = (seg.profile.speed_after(s), self.params.accel_um_s2);
        if v <= 0.0 || a <= 0.0 {
            drop(st);
            self.stop();
            return Duration::ZERO;
        }
        // The second half of a triangle peaking at `v` now: it ends `v/a` later, `v²/2a` on.
        let x = seg.position_at(now);
        let dir = (seg.profile.to_um - seg.profile.from_um).signum();
        let (t, half) = (v / a, v * v / (2.0 * a));
        let profile = Profile {
            from_um: x - dir * half,
            to_um: x + dir * half,
            t_acc: t,
            t_flat: 0.0,
            v_peak: v,
            accel: a,
        };
        let dt = Duration::from_secs_f64(t);
        st.segment = Some(Segment {
            start: now.checked_sub(dt).unwrap_or(now),
            profile,
        });
        st.rest_um = profile.to_um;
        st.commanded_um = profile.to_um;
        dt
    }

    /// Where the controller believes the axis ends up: the last commanded target.
    pub fn commanded_um(&self) -> f64 {
        self.lock().commanded_um
    }

    /// Set the position without moving (homing sets the origin).
    pub fn set_position(&self, position_um: f64) {
        let mut st = self.lock();
        st.segment = None;
        st.rest_um = position_um;
        st.commanded_um = position_um;
    }

    fn position_locked(st: &State, t: Instant) -> f64 {
        match &st.segment {
            Some(seg) if t < seg.start + seg.duration() => seg.position_at(t),
            _ => st.rest_um,
        }
    }

    /// True position at instant `t` (what an interferometer sees): the carriage's position
    /// plus the leadscrew's periodic error there.
    pub fn position_at(&self, t: Instant) -> f64 {
        self.leadscrew
            .true_um(Self::position_locked(&self.lock(), t))
    }

    /// The controller's position: the last commanded target once motion is done, the
    /// profile position while moving (it counts steps, it does not see the error).
    pub fn reported_um(&self, t: Instant) -> f64 {
        let st = self.lock();
        match &st.segment {
            Some(seg) if t < seg.start + seg.duration() => seg.position_at(t),
            _ => st.commanded_um,
        }
    }

    pub fn is_moving(&self, t: Instant) -> bool {
        let st = self.lock();
        matches!(&st.segment, Some(seg) if t < seg.start + seg.duration())
    }

    /// The move in progress: when it started and its profile (what a test checks a
    /// controller's speed on, in the model's time rather than the wall clock's).
    pub fn current_move(&self) -> Option<(Instant, Profile)> {
        let st = self.lock();
        match &st.segment {
            Some(seg) if Instant::now() < seg.start + seg.duration() => {
                Some((seg.start, seg.profile))
            }
            _ => None,
        }
    }

    /// When the current move ends (now, if idle).
    pub fn move_ends_at(&self) -> Instant {
        let st = self.lock();
        match &st.segment {
            Some(seg) => (seg.start + seg.duration()).max(Instant::now()),
            None => Instant::now(),
        }
    }
}

impl TruePosition for Axis {
    fn true_position_um(&self, t: Instant) -> [f64; 2] {
        [self.position_at(t), 0.0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_50um_move_takes_time_and_ends_near_the_target() {
        let axis = Axis::new(AxisParams::default());
        let d = axis.command_move(50.0).unwrap();
        // Triangle profile: 2*sqrt(d/a) = 2*sqrt(50/5e5) = 20 ms.
        assert!((d.as_secs_f64() - 0.020).abs() < 1e-3, "{d:?}");
        let t0 = Instant::now();
        let mid = axis.position_at(t0 + d / 2);
        assert!(mid > 10.0 && mid < 40.0, "mid-move position {mid}");
        let end = axis.position_at(t0 + d * 2);
        assert!((end - 50.0).abs() < 10.0, "end {end}");
        assert_eq!(axis.reported_um(t0 + d * 2), 50.0);
    }

    #[test]
    fn a_slower_move_cruises_at_its_own_speed_with_the_same_acceleration() {
        let p = AxisParams::default();
        let fast = Profile::plan(0.0, 10_000.0, &p);
        let slow = Profile::plan_at(0.0, 10_000.0, &p, 5_000.0);
        assert_eq!(fast.peak_speed_um_s(), 20_000.0);
        assert_eq!(slow.peak_speed_um_s(), 5_000.0);
        // 10 mm at 5 mm/s: 2 s cruising plus v/a = 10 ms for the ramps.
        assert!(
            (slow.duration_s() - 2.010).abs() < 1e-9,
            "{}",
            slow.duration_s()
        );
        assert!(
            (fast.duration_s() - 0.540).abs() < 1e-9,
            "{}",
            fast.duration_s()
        );
        // Same acceleration: both ramps cover the first 1 ms identically.
        assert_eq!(slow.position_after(0.001), fast.position_after(0.001));
        // One second in, the slow move is ~5 mm along; the fast one is past 10 mm's half.
        assert!((slow.position_after(1.0) - 4_975.0).abs() < 1e-6);
        assert_eq!(slow.position_after(3.0), 10_000.0);
        // Clamped to the top speed; nonsense speeds mean the top speed.
        for v in [1e9, 0.0, -1.0, f64::NAN] {
            let q = Profile::plan_at(0.0, 10_000.0, &p, v);
            assert_eq!(q.peak_speed_um_s(), 20_000.0, "speed {v}");
        }
        // A short move never reaches a high cruise speed: triangle profile.
        let short = Profile::plan_at(0.0, 50.0, &p, 15_000.0);
        assert!((short.peak_speed_um_s() - 5_000.0).abs() < 1e-9);
    }

    #[test]
    fn command_move_at_plans_the_move_it_reports() {
        let axis = Axis::new(AxisParams {
            position_error_rms_um: 0.0,
            ..AxisParams::default()
        });
        assert!(axis.current_move().is_none());
        let d = axis.command_move_at(2_000.0, 4_000.0).unwrap();
        let (start, prof) = axis.current_move().unwrap();
        assert_eq!(prof.peak_speed_um_s(), 4_000.0);
        assert!((d.as_secs_f64() - prof.duration_s()).abs() < 1e-6);
        assert!((prof.duration_s() - 0.508).abs() < 1e-9);
        let quarter = axis.position_at(start + Duration::from_millis(129));
        assert!((quarter - 500.0).abs() < 1.0, "{quarter}");
    }

    #[test]
    fn past_the_hard_limit_is_refused() {
        let axis = Axis::new(AxisParams::default());
        assert!(matches!(
            axis.command_move(-1e6),
            Err(MotionError::HardLimit { .. })
        ));
    }
}
