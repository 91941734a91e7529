//! When jobs start and end, and how long they will take: the `started_at`, `elapsed_s` and
//! `eta_s` of `status` and `list` (docs/protocol.md, "Status").
//!
//! A frame's time is the interval between two recorded steps: move + settle + grab + the
//! disk, as this rig does them. The running job's estimate is the median of its own last
//! intervals (`measured`); a job that has not measured two yet uses the rig's recent steps
//! from earlier jobs, less their settle, plus its own settle (`rig`); before any step on
//! this daemon, a guess from the settings: the job's and the stage's settle plus
//! [`MOVE_GRAB_GUESS_S`] (`settings`). Medians, so a pause or one slow frame does not
//! swing the estimate.
//!
//! A job with `interval_s` starts each repeat that long after the previous one started (the
//! engine's rule, `acquisition::engine`), or when the previous one ends if that is later:
//! the estimate follows the same rule from the current repeat's start. The interval that
//! holds such a wait is not a frame's time and is not measured.

pub use crate::timestamps::{rfc3339, rfc3339_unix};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::time::{Duration, Instant, SystemTime};

/// Step intervals kept per job and for the rig (the median of these is the estimate).
const KEEP: usize = 64;
/// Move + grab of one frame before any was measured: a few hundred µm at a GRBL's feed and
/// one frame at 30 fps, rounded up.
pub const MOVE_GRAB_GUESS_S: f64 = 0.1;

/// Where a job's per-frame time comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum EtaBasis {
    /// The job's own recorded steps (median interval).
    Measured,
    /// Earlier jobs' steps on this rig (median interval less their settle, plus this job's).
    Rig,
    /// No step recorded yet on this daemon: the settle times plus a fixed move + grab guess.
    Settings,
}

/// The timing fields of a job's status; each absent when it does not apply (a queued job has
/// no `started_at`, a finished one no `eta_s`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct JobTiming {
    /// When it started running (RFC 3339, UTC).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub started_at: Option<String>,
    /// When it ended (RFC 3339, UTC).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ended_at: Option<String>,
    /// Seconds it has run (running) or ran (ended).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elapsed_s: Option<f64>,
    /// A queued job: when it is expected to start (RFC 3339, UTC), and in how many seconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expected_start_at: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub starts_in_s: Option<f64>,
    /// Running or queued: seconds from now until it is expected to end.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eta_s: Option<f64>,
    /// The seconds per frame the estimate uses, and where they come from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_s: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eta_basis: Option<EtaBasis>,
}

/// The median of `v` (None when empty).
fn median(v: &VecDeque<f64>) -> Option<f64> {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if s.is_empty() {
        return None;
    }
    s.sort_unstable_by(f64::total_cmp);
    let n = s.len();
    Some(match n % 2 {
        1 => s[n / 2],
        _ => (s[n / 2 - 1] + s[n / 2]) / 2.0,
    })
}

fn push(v: &mut VecDeque<f64>, x: f64) {
    if v.len() == KEEP {
        v.pop_front();
    }
    v.push_back(x);
}

/// A job's repeats as its timing sees them: frames in each, and `interval_s` between their
/// starts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Repeats {
    pub frames: u32,
    pub interval_s: Option<f64>,
}

impl Repeats {
    /// Every frame in one repeat, no interval.
    pub fn one(total_frames: u32) -> Repeats {
        Repeats {
            frames: total_frames,
            interval_s: None,
        }
    }

    /// The frames per repeat of a plan of `count` repeats (at least one frame each).
    pub fn of(total_frames: u32, count: u32, interval_s: Option<f64>) -> Repeats {
        Repeats {
            frames: (total_frames / count.max(1)).max(1),
            interval_s,
        }
    }

    /// Whether the `index`-th frame (0-based) is the first of a repeat after the first.
    fn opens_repeat(&self, index: u32) -> bool {
        index > 0 && index.is_multiple_of(self.frames.max(1))
    }
}

/// One job's clock: when it started and ended, its last step intervals.
#[derive(Debug, Clone, Default)]
pub struct JobClock {
    started: Option<(SystemTime, Instant)>,
    ended: Option<SystemTime>,
    last_step: Option<Instant>,
    /// When the current repeat started, by the engine's rule.
    repeat_started: Option<Instant>,
    intervals: VecDeque<f64>,
    /// Since when the job is paused: its estimate stands still meanwhile.
    paused_at: Option<Instant>,
}

impl JobClock {
    pub fn start(&mut self, now: Instant, wall: SystemTime) {
        self.started = Some((wall, now));
        self.last_step = Some(now);
        self.repeat_started = Some(now);
    }

    pub fn end(&mut self, wall: SystemTime) {
        self.ended.get_or_insert(wall);
    }

    /// The job paused at `now`: time stands still for its estimate until [`JobClock::resume`].
    pub fn pause(&mut self, now: Instant) {
        self.paused_at.get_or_insert(now);
    }

    /// The job goes on at `now`: the pause is left out of its step and repeat times.
    pub fn resume(&mut self, now: Instant) {
        if let Some(p) = self.paused_at.take() {
            let d = now.saturating_duration_since(p);
            self.last_step = self.last_step.map(|t| t + d);
            self.repeat_started = self.repeat_started.map(|t| t + d);
        }
    }

    /// `now`, or when the job paused if it is paused.
    fn frozen(&self, now: Instant) -> Instant {
        self.paused_at.unwrap_or(now)
    }

    /// The `frames_done`-th step was recorded at `now`: the interval since the one before
    /// (or the start), `None` when there is none or it holds a wait between repeats.
    pub fn step(&mut self, now: Instant, frames_done: u32, repeats: &Repeats) -> Option<f64> {
        let last = self.last_step.replace(now);
        let index = frames_done.saturating_sub(1);
        let mut waited = false;
        if repeats.opens_repeat(index) {
            // The engine started this repeat `interval_s` after the last one started, or
            // when the last one ended if that was later.
            let ended = last.unwrap_or(now);
            let due = match (self.repeat_started, repeats.interval_s) {
                (Some(s), Some(i)) => {
                    waited = true;
                    let i = Duration::try_from_secs_f64(i).unwrap_or_default();
                    s.checked_add(i).unwrap_or(ended).max(ended)
                }
                _ => ended,
            };
            self.repeat_started = Some(due.min(now));
        }
        let dt = last.map(|t| now.duration_since(t).as_secs_f64())?;
        if waited {
            return None;
        }
        push(&mut self.intervals, dt);
        Some(dt)
    }

    /// The job's own seconds per frame, once two intervals are measured (the first one holds
    /// the move to the start and the session's creation).
    pub fn measured_frame_s(&self) -> Option<f64> {
        (self.intervals.len() >= 2)
            .then(|| median(&self.intervals))
            .flatten()
    }

    /// Seconds since the last step (or the start).
    fn since_last_step(&self, now: Instant) -> f64 {
        let now = self.frozen(now);
        self.last_step
            .map_or(0.0, |t| now.saturating_duration_since(t).as_secs_f64())
    }

    /// Seconds since the current repeat started (or the job did).
    fn since_repeat_start(&self, now: Instant) -> f64 {
        let now = self.frozen(now);
        self.repeat_started
            .map_or(0.0, |t| now.saturating_duration_since(t).as_secs_f64())
    }
}

/// Seconds from now until a job ends, at `frame_s` a frame: `done` of `total` frames
/// recorded, the last `since_last_s` ago, its current repeat started `since_repeat_s` ago.
/// Each later repeat starts `interval_s` after the one before started, or when it ends if
/// that is later.
fn remaining_s(
    (done, total): (u32, u32),
    repeats: &Repeats,
    frame_s: f64,
    since_last_s: f64,
    since_repeat_s: f64,
) -> f64 {
    let per = repeats.frames.max(1);
    let done = done.min(total);
    let in_repeat = done % per;
    // The end of the repeat under way, relative to now (the last step, if it ended one).
    let mut t = -since_last_s;
    let mut next = done / per;
    if in_repeat > 0 || done == 0 {
        t += (per - in_repeat).min(total - done) as f64 * frame_s;
        next += 1;
    }
    let reps_total = total.div_ceil(per);
    let left = reps_total.saturating_sub(next) as f64;
    let repeat_s = per as f64 * frame_s;
    let t = match repeats.interval_s {
        Some(i) if left > 0.0 => {
            // The next repeat starts `i` after the current one started, or when it ends;
            // the ones after it `i` apart, or back to back if a repeat takes longer.
            let first = (-since_repeat_s + i).max(t);
            first + (left - 1.0) * i.max(repeat_s) + repeat_s
        }
        _ => t + left * repeat_s,
    };
    t.max(0.0)
}

/// Seconds a whole job takes, from its start.
fn duration_s(total: u32, repeats: &Repeats, frame_s: f64) -> f64 {
    remaining_s((0, total), repeats, frame_s, 0.0, 0.0)
}

/// The rig's recent step intervals, less each job's own settle: the part of a frame that is
/// the rig's (move, the stage's settle, grab, disk).
#[derive(Debug, Clone, Default)]
pub struct RigPace {
    overheads: VecDeque<f64>,
}

impl RigPace {
    pub fn record(&mut self, interval_s: f64, job_settle_s: f64) {
        push(&mut self.overheads, (interval_s - job_settle_s).max(0.0));
    }

    /// Seconds per frame for a job that settles `settle_s`, and the basis; `stage_settle_s`
    /// is the stage's own settle, used only before anything was measured.
    pub fn frame_s(&self, settle_s: f64, stage_settle_s: f64) -> (f64, EtaBasis) {
        match median(&self.overheads) {
            Some(o) => (o + settle_s, EtaBasis::Rig),
            None => (
                settle_s + stage_settle_s + MOVE_GRAB_GUESS_S,
                EtaBasis::Settings,
            ),
        }
    }
}

/// What an estimate needs of one pending job.
pub struct Pending<'a> {
    pub clock: &'a JobClock,
    pub frames_done: u32,
    pub total_frames: u32,
    pub repeats: Repeats,
    /// Its settle and its stage's, seconds.
    pub settle_s: f64,
    pub stage_settle_s: f64,
}

/// Timings of the running job (if any) and the queued ones in queue order: each queued job
/// starts when the one before it is expected to end.
pub fn estimate(
    pace: &RigPace,
    running: Option<Pending<'_>>,
    queued: &[Pending<'_>],
    now: Instant,
    wall: SystemTime,
) -> (Option<JobTiming>, Vec<JobTiming>) {
    let frame_s = |p: &Pending<'_>| match p.clock.measured_frame_s() {
        Some(f) => (f, EtaBasis::Measured),
        None => pace.frame_s(p.settle_s, p.stage_settle_s),
    };
    let mut t = 0.0;
    let running = running.map(|p| {
        let (f, basis) = frame_s(&p);
        t = remaining_s(
            (p.frames_done, p.total_frames),
            &p.repeats,
            f,
            p.clock.since_last_step(now),
            p.clock.since_repeat_start(now),
        );
        JobTiming {
            eta_s: Some(t),
            frame_s: Some(f),
            eta_basis: Some(basis),
            ..ended_or_running(p.clock, now)
        }
    });
    let queued = queued
        .iter()
        .map(|p| {
            let (f, basis) = frame_s(p);
            let starts_in = t;
            t += duration_s(p.total_frames, &p.repeats, f);
            JobTiming {
                expected_start_at: rfc3339_unix(crate::timestamps::unix_s(wall) + starts_in),
                starts_in_s: Some(starts_in),
                eta_s: Some(t),
                frame_s: Some(f),
                eta_basis: Some(basis),
                ..JobTiming::default()
            }
        })
        .collect();
    (running, queued)
}

/// `started_at`, `ended_at` and `elapsed_s` of a job that has started.
pub fn ended_or_running(c: &JobClock, now: Instant) -> JobTiming {
    let Some((started_wall, started)) = c.started else {
        return JobTiming::default();
    };
    let elapsed = match c.ended {
        Some(end) => end
            .duration_since(started_wall)
            .unwrap_or_default()
            .as_secs_f64(),
        None => now.saturating_duration_since(started).as_secs_f64(),
    };
    JobTiming {
        started_at: Some(rfc3339(started_wall)),
        ended_at: c.ended.map(rfc3339),
        elapsed_s: Some(elapsed),
        ..JobTiming::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn clock_with_steps(t0: Instant, steps_s: &[f64]) -> JobClock {
        clock_with_repeats(t0, steps_s, &Repeats::one(1000))
    }

    fn clock_with_repeats(t0: Instant, steps_s: &[f64], repeats: &Repeats) -> JobClock {
        let mut c = JobClock::default();
        c.start(
            t0,
            SystemTime::UNIX_EPOCH + Duration::from_secs(1_764_633_600),
        );
        let mut t = t0;
        for (i, &s) in steps_s.iter().enumerate() {
            t += Duration::from_secs_f64(s);
            c.step(t, i as u32 + 1, repeats);
        }
        c
    }

    fn pending(
        clock: &JobClock,
        frames_done: u32,
        total_frames: u32,
        repeats: Repeats,
    ) -> Pending<'_> {
        Pending {
            clock,
            frames_done,
            total_frames,
            repeats,
            settle_s: 0.02,
            stage_settle_s: 0.0,
        }
    }

    /// 3 repeats of 10 frames, 60 s apart (`interval_s`), at 0.5 s a frame.
    const EVERY_MINUTE: Repeats = Repeats {
        frames: 10,
        interval_s: Some(60.0),
    };

    #[test]
    fn the_eta_stands_still_while_the_job_is_paused() {
        let t0 = Instant::now();
        let wall = SystemTime::UNIX_EPOCH + Duration::from_secs(1_764_633_600);
        let mut c = clock_with_repeats(t0, &[0.5; 4], &Repeats::one(10));
        let eta = |c: &JobClock, at_s: f64| {
            let now = t0 + Duration::from_secs_f64(at_s);
            let p = pending(c, 4, 10, Repeats::one(10));
            estimate(&RigPace::default(), Some(p), &[], now, wall)
                .0
                .unwrap()
                .eta_s
                .unwrap()
        };
        // 6 frames left at 0.5 s, the last one 0.2 s ago: 2.8 s.
        assert!((eta(&c, 2.2) - 2.8).abs() < 1e-9);
        c.pause(t0 + Duration::from_secs_f64(2.2));
        assert!((eta(&c, 2.2) - 2.8).abs() < 1e-9);
        assert!(
            (eta(&c, 62.2) - 2.8).abs() < 1e-9,
            "a minute paused: still 2.8 s"
        );
        // Resumed after that minute: it counts down from there.
        c.resume(t0 + Duration::from_secs_f64(62.2));
        assert!((eta(&c, 62.7) - 2.3).abs() < 1e-9, "{}", eta(&c, 62.7));
    }

    #[test]
    fn the_eta_counts_the_waits_between_repeats() {
        let t0 = Instant::now();
        let wall = SystemTime::UNIX_EPOCH + Duration::from_secs(1_764_633_600);
        // The first repeat done (10 frames at 0.5 s), 0.2 s ago.
        let c = clock_with_repeats(t0, &[0.5; 10], &EVERY_MINUTE);
        let now = t0 + Duration::from_secs_f64(5.2);
        let (r, q) = estimate(
            &RigPace::default(),
            Some(pending(&c, 10, 30, EVERY_MINUTE)),
            &[pending(&JobClock::default(), 0, 30, EVERY_MINUTE)],
            now,
            wall,
        );
        let r = r.unwrap();
        assert_eq!(r.frame_s, Some(0.5));
        // The second repeat starts at 60 s, the third at 120 s and takes 5 s: 125 - 5.2.
        assert!((r.eta_s.unwrap() - 119.8).abs() < 1e-9, "{r:?}");
        // A queued job of the same plan starts then and takes 2 minutes and 5 s; its frame
        // time is the rig's, which holds no wait either (none was recorded: the settings').
        let q = &q[0];
        assert!((q.starts_in_s.unwrap() - 119.8).abs() < 1e-9, "{q:?}");
        let f = q.frame_s.unwrap();
        assert!(
            (q.eta_s.unwrap() - (119.8 + 120.0 + 10.0 * f)).abs() < 1e-9,
            "{q:?}"
        );

        // The first frame of the second repeat, taken after the wait (the engine started the
        // repeat at 60 s): its 55.5 s interval is not a frame's time.
        let mut steps = vec![0.5; 10];
        steps.push(55.5);
        let c = clock_with_repeats(t0, &steps, &EVERY_MINUTE);
        assert_eq!(c.measured_frame_s(), Some(0.5));
        let now = t0 + Duration::from_secs_f64(61.0);
        let (r, _) = estimate(
            &RigPace::default(),
            Some(pending(&c, 11, 30, EVERY_MINUTE)),
            &[],
            now,
            wall,
        );
        // 9 frames of the second repeat (4.5 s, the last frame 0.5 s ago), then the third
        // at 120 s: 125 - 61.
        assert!((r.unwrap().eta_s.unwrap() - 64.0).abs() < 1e-9);
    }

    #[test]
    fn repeats_longer_than_their_interval_run_back_to_back() {
        let t0 = Instant::now();
        let every_2s = Repeats {
            frames: 10,
            interval_s: Some(2.0),
        };
        let c = clock_with_repeats(t0, &[0.5; 4], &every_2s);
        let (r, q) = estimate(
            &RigPace::default(),
            Some(pending(&c, 4, 30, every_2s)),
            &[pending(&JobClock::default(), 0, 30, Repeats::one(30))],
            t0 + Duration::from_secs_f64(2.0),
            SystemTime::now(),
        );
        // 26 frames left at 0.5 s, no wait anywhere.
        assert!((r.unwrap().eta_s.unwrap() - 13.0).abs() < 1e-9);
        assert!((q[0].starts_in_s.unwrap() - 13.0).abs() < 1e-9);
        // Without `interval_s` a repeat's first interval is a frame's time like any.
        let c = clock_with_repeats(
            t0,
            &[0.5; 10].iter().chain(&[0.7]).copied().collect::<Vec<_>>(),
            &Repeats::one(10),
        );
        assert_eq!(c.measured_frame_s(), Some(0.5));
        assert_eq!(c.intervals.len(), 11);
    }

    #[test]
    fn times_are_rfc3339_utc_to_the_second() {
        let t = SystemTime::UNIX_EPOCH + Duration::from_millis(1_764_633_600_750);
        assert_eq!(rfc3339(t), "2025-12-02T00:00:00Z");
        assert_eq!(rfc3339_unix(0.0), None);
        // Numbers from a manifest the formatter cannot write are no time, never a panic.
        for v in [1e300, 1e11, f64::NAN, f64::INFINITY, -1e308, -0.0] {
            assert_eq!(rfc3339_unix(v), None, "{v}");
        }
        assert_eq!(rfc3339_unix(1e10).as_deref(), Some("2286-11-20T17:46:40Z"));
    }

    #[test]
    fn the_running_job_uses_its_median_interval_and_the_queue_follows_it() {
        let t0 = Instant::now();
        // 5 frames: the first interval (move to the start) is slow, one frame is slower.
        let run = clock_with_steps(t0, &[3.0, 0.5, 0.5, 2.0, 0.5]);
        let now = t0 + Duration::from_secs_f64(6.5 + 0.2);
        let queued_clock = JobClock::default();
        let wall = SystemTime::UNIX_EPOCH + Duration::from_secs(1_764_633_600);
        let mut pace = RigPace::default();
        pace.record(0.45, 0.02);
        let (r, q) = estimate(
            &pace,
            Some(Pending {
                clock: &run,
                frames_done: 5,
                total_frames: 25,
                repeats: Repeats::one(25),
                settle_s: 0.02,
                stage_settle_s: 0.0,
            }),
            &[Pending {
                clock: &queued_clock,
                frames_done: 0,
                total_frames: 10,
                repeats: Repeats::one(10),
                settle_s: 0.5,
                stage_settle_s: 0.0,
            }],
            now,
            wall,
        );
        let r = r.unwrap();
        assert_eq!(r.eta_basis, Some(EtaBasis::Measured));
        assert_eq!(r.frame_s, Some(0.5));
        // 20 frames at 0.5 s, less the 0.2 s since the last one.
        assert!((r.eta_s.unwrap() - 9.8).abs() < 1e-9, "{r:?}");
        assert!((r.elapsed_s.unwrap() - 6.7).abs() < 1e-9);
        // The queued job: the rig's overhead (0.43 s) plus its own 0.5 s settle a frame.
        let q = &q[0];
        assert_eq!(q.eta_basis, Some(EtaBasis::Rig));
        assert!((q.frame_s.unwrap() - 0.93).abs() < 1e-9);
        assert!((q.starts_in_s.unwrap() - 9.8).abs() < 1e-9);
        assert!((q.eta_s.unwrap() - (9.8 + 9.3)).abs() < 1e-9);
        assert_eq!(q.expected_start_at.as_deref(), Some("2025-12-02T00:00:09Z"));
    }

    #[test]
    fn before_any_step_the_estimate_comes_from_the_settings() {
        let c = JobClock::default();
        let (_, q) = estimate(
            &RigPace::default(),
            None,
            &[Pending {
                clock: &c,
                frames_done: 0,
                total_frames: 20,
                repeats: Repeats::one(20),
                settle_s: 0.02,
                stage_settle_s: 0.05,
            }],
            Instant::now(),
            SystemTime::now(),
        );
        assert_eq!(q[0].eta_basis, Some(EtaBasis::Settings));
        assert!((q[0].eta_s.unwrap() - 20.0 * (0.07 + MOVE_GRAB_GUESS_S)).abs() < 1e-9);
        assert_eq!(q[0].starts_in_s, Some(0.0));
    }
}
