//! The interferometer as a job sees it: the XL-80's log file, followed while the laser
//! software writes it. One implementation for both rigs — `rigd --config` follows `[xl80]
//! path`, `rigd --sim` follows the file its simulated XL-80 writes live — so every sim job
//! runs the hardware path. (`daemon::interferometer` records what it reads in the session.)
//!
//! Per frame the runner asks for the reading at the frame's exposure time; the log is
//! polled until it holds a sample at or after that time (or a deadline passes), and the
//! reading is interpolated linearly between the two samples around it. Every sample read
//! from the job's start on is handed to the session (`interferometer.csv`).
//!
//! Sample times are the log's start date plus the sample's time, minus `log_minus_pc_s`,
//! the log clock minus the PC clock. That offset is estimated while the log grows: a sample
//! cannot be read before it was taken, so each sample that appears between two polls bounds
//! it from below (`log time - read time`), and the largest bound is kept. It converges to
//! the true offset less the writer's shortest delay (a few ms when the writer flushes
//! promptly). It absorbs the formats' whole-second dates (a capture started mid-second is
//! up to 1 s off otherwise) and a log written in local time. The backlog read on the first
//! poll says nothing (it may be an old file), so until the log has grown under observation
//! the offset is 0: the date is taken as written.
//!
//! While a job records, the offset in use is held: a bound that tightens mid-job is kept for
//! the next job. Re-timing samples mid-job would step the recorded times back (by the few ms
//! the estimate gained), and the session's log must stay in time order with every frame's
//! reading recomputable from it.

use crate::hw::devices::{LogSample, LogSource, PositionLog};
use crate::timestamps::unix_s;
use crate::xl80::Follower;
use std::collections::VecDeque;
use std::time::{Duration, Instant, SystemTime};

/// At a job's start, watch the log grow this many times (for the clock offset), for at
/// most `WARM_UP`.
const WARM_UP_GROWTHS: usize = 3;
const WARM_UP: Duration = Duration::from_millis(300);
/// Samples kept behind the newest one for interpolation.
const KEEP_S: f64 = 2.0;
/// Two samples further apart than this (or one this far from `t`) do not say where the
/// stage was at `t`.
const MAX_GAP_S: f64 = 0.25;

/// A growing XL-80 log as the rig's [`PositionLog`].
pub struct FollowedLog {
    follower: Follower,
    poll: Duration,
    max_wait: Duration,
    /// Log clock minus PC clock (s): the estimate, once the log has grown under observation.
    log_minus_pc_s: Option<f64>,
    /// The tightest bound seen, applied when no job records.
    best_bound_s: Option<f64>,
    /// Growth observations behind the estimate.
    growths: usize,
    /// A job records samples: the offset in use is held.
    recording: bool,
    restarts: usize,
    /// Recent samples, oldest first, for interpolation.
    recent: VecDeque<LogSample>,
    /// Samples from the job's start not yet taken by the session.
    pending: Vec<LogSample>,
    from_unix_s: f64,
    /// The log did not reach the last asked time before the deadline: do not wait again
    /// until it grows.
    stalled: bool,
    untimed: usize,
    last_error: Option<String>,
}

impl FollowedLog {
    /// Follow `follower`'s file, polling every `poll` while waiting for a frame's sample.
    pub fn new(follower: Follower, poll: Duration) -> FollowedLog {
        let poll = poll.max(Duration::from_millis(1));
        FollowedLog {
            follower,
            poll,
            max_wait: (poll * 5).max(Duration::from_secs(1)),
            log_minus_pc_s: None,
            best_bound_s: None,
            growths: 0,
            recording: false,
            restarts: 0,
            recent: VecDeque::new(),
            pending: Vec::new(),
            from_unix_s: f64::INFINITY,
            stalled: false,
            untimed: 0,
            last_error: None,
        }
    }

    /// The log clock minus the PC clock in use, seconds (0 until estimated).
    pub fn log_minus_pc_s(&self) -> f64 {
        self.log_minus_pc_s.unwrap_or(0.0)
    }

    /// Take a lower bound of the clock offset; apply it unless a job records.
    fn bound_offset(&mut self, bound_s: f64) {
        self.best_bound_s = Some(self.best_bound_s.map_or(bound_s, |o| o.max(bound_s)));
        self.growths += 1;
        if !self.recording || self.log_minus_pc_s.is_none() {
            self.apply_best_bound();
        }
    }

    /// Use the tightest bound seen; re-time the samples held in memory.
    fn apply_best_bound(&mut self) {
        let Some(new) = self.best_bound_s else {
            return;
        };
        let old = self.log_minus_pc_s();
        self.log_minus_pc_s = Some(new);
        let shift = old - new;
        if shift != 0.0 {
            for x in self.recent.iter_mut().chain(self.pending.iter_mut()) {
                x.t_unix_s += shift;
            }
        }
    }

    /// Read what the file gained; true if it gained samples.
    fn catch_up(&mut self) -> bool {
        // Bytes appearing now were written since the last poll only if that poll read the file.
        let watching = self.follower.offset() > 0;
        let new = match self.follower.poll() {
            Ok(n) => {
                self.last_error = None;
                n
            }
            Err(e) => {
                let e = e.to_string();
                if self.last_error.as_ref() != Some(&e) {
                    tracing::warn!("xl80 log: {e}");
                    self.last_error = Some(e);
                }
                return false;
            }
        };
        let read_at = unix_s(SystemTime::now());
        let restarted = self.follower.restarts() != self.restarts;
        if restarted {
            // A new capture replaced the file: a new date, a new offset.
            self.restarts = self.follower.restarts();
            self.log_minus_pc_s = None;
            self.best_bound_s = None;
            self.growths = 0;
            self.recent.clear();
        }
        let newest_log_s = new
            .iter()
            .rev()
            .find_map(|r| self.follower.log().time_of(r))
            .map(unix_s);
        if let (true, false, Some(l)) = (watching, restarted, newest_log_s) {
            self.bound_offset(l - read_at);
        }
        let offset = self.log_minus_pc_s();
        let log = self.follower.log();
        for r in &new {
            let Some(at) = log.time_of(r) else {
                self.untimed += 1;
                if self.untimed == 1 {
                    tracing::warn!(
                        "xl80 log {}: readings without a time (no date or time column): \
                         they cannot be matched to frames",
                        self.follower.path().display()
                    );
                }
                continue;
            };
            let s = LogSample {
                t_unix_s: unix_s(at) - offset,
                position_um: r.position_um,
                sample: r.line,
            };
            if s.t_unix_s >= self.from_unix_s {
                self.pending.push(s);
            }
            self.recent.push_back(s);
        }
        self.follower.forget_readings();
        if let Some(newest) = self.recent.back().map(|s| s.t_unix_s) {
            while self.recent.len() > 2 && self.recent[1].t_unix_s < newest - KEEP_S {
                self.recent.pop_front();
            }
        }
        if !new.is_empty() {
            self.stalled = false;
        }
        !new.is_empty()
    }

    fn newest_s(&self) -> Option<f64> {
        self.recent.back().map(|s| s.t_unix_s)
    }
}

/// The reading at `t` from samples sorted by time: linear between the two around it, or the
/// nearest end sample when `t` is just outside them.
pub fn interpolate(samples: &VecDeque<LogSample>, t: f64) -> Option<f64> {
    let after = samples.partition_point(|s| s.t_unix_s < t);
    match (
        after.checked_sub(1).and_then(|i| samples.get(i)),
        samples.get(after),
    ) {
        (Some(a), Some(b)) => {
            if b.t_unix_s - a.t_unix_s > MAX_GAP_S {
                return None;
            }
            let span = b.t_unix_s - a.t_unix_s;
            if span <= 0.0 {
                return Some(b.position_um);
            }
            let w = (t - a.t_unix_s) / span;
            Some(a.position_um + w * (b.position_um - a.position_um))
        }
        (Some(a), None) => (t - a.t_unix_s <= MAX_GAP_S).then_some(a.position_um),
        (None, Some(b)) => (b.t_unix_s - t <= MAX_GAP_S).then_some(b.position_um),
        (None, None) => None,
    }
}

impl PositionLog for FollowedLog {
    fn begin(&mut self, from: SystemTime) {
        self.recording = false;
        self.apply_best_bound();
        self.from_unix_s = unix_s(from);
        self.pending.clear();
        self.catch_up();
        // Watch the log grow a few times before the first frame, so the clock offset is
        // settled before samples are recorded (once per log: later jobs reuse it).
        let until = Instant::now() + WARM_UP;
        while self.growths < WARM_UP_GROWTHS && Instant::now() < until {
            std::thread::sleep(self.poll);
            self.catch_up();
        }
        let from = self.from_unix_s;
        self.pending.retain(|s| s.t_unix_s >= from);
        self.recording = true;
    }

    fn position_at(&mut self, t: SystemTime) -> Option<f64> {
        let t = unix_s(t);
        let deadline = Instant::now() + self.max_wait;
        loop {
            self.catch_up();
            if self.newest_s().is_some_and(|n| n >= t) {
                break;
            }
            if self.stalled || Instant::now() >= deadline {
                if !self.stalled {
                    tracing::warn!(
                        "xl80 log {}: no sample at or after {t:.3} within {:?} (newest: {:?})",
                        self.follower.path().display(),
                        self.max_wait,
                        self.newest_s()
                    );
                }
                self.stalled = true;
                break;
            }
            std::thread::sleep(self.poll);
        }
        interpolate(&self.recent, t)
    }

    fn take_samples(&mut self) -> Vec<LogSample> {
        std::mem::take(&mut self.pending)
    }

    fn end(&mut self) {
        // Samples read between jobs (by `reading_now`) belong to no session.
        self.from_unix_s = f64::INFINITY;
        self.pending.clear();
        self.recording = false;
        self.apply_best_bound();
    }

    fn reading_now(&mut self) -> Result<LogSample, String> {
        self.catch_up();
        let now = unix_s(SystemTime::now());
        let path = self.follower.path().display();
        match self.recent.back() {
            Some(s) if now - s.t_unix_s <= MAX_GAP_S => Ok(*s),
            Some(s) => Err(format!(
                "the xl80 log {path} has not grown for {:.1} s: is the laser's capture running?",
                now - s.t_unix_s
            )),
            None => Err(format!("the xl80 log {path} holds no timed reading yet")),
        }
    }

    fn source(&self) -> LogSource {
        let log = self.follower.log();
        LogSource {
            path: self.follower.path().display().to_string(),
            format: format!("{:?}", log.format).to_lowercase(),
            um_per_unit: log.um_per_unit,
            sample_rate_hz: log.sample_rate_hz,
            date: log.meta.date.clone(),
            log_minus_pc_s: self.log_minus_pc_s(),
            clock: if self.log_minus_pc_s.is_some() {
                format!(
                    "estimated from {} growths of the log under observation (held while a job records)",
                    self.growths
                )
            } else {
                "the log's date as written (it has not grown under observation)".into()
            },
            fields: log.meta.fields.clone(),
            garbled: log.garbled.count,
            replayed_from: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn s(t: f64, p: f64) -> LogSample {
        LogSample {
            t_unix_s: t,
            position_um: p,
            sample: 0,
        }
    }

    #[test]
    fn interpolates_between_neighbours_and_refuses_gaps() {
        let v: VecDeque<_> = [s(10.0, 0.0), s(10.01, 1.0), s(10.02, 3.0), s(11.0, 9.0)].into();
        assert!((interpolate(&v, 10.005).unwrap() - 0.5).abs() < 1e-9);
        assert!((interpolate(&v, 10.015).unwrap() - 2.0).abs() < 1e-9);
        assert_eq!(interpolate(&v, 10.01), Some(1.0));
        // Inside a gap of almost a second: unknown.
        assert_eq!(interpolate(&v, 10.5), None);
        // Just outside the ends: the end sample; far outside: unknown.
        assert_eq!(interpolate(&v, 9.9), Some(0.0));
        assert_eq!(interpolate(&v, 11.1), Some(9.0));
        assert_eq!(interpolate(&v, 12.0), None);
        assert_eq!(interpolate(&VecDeque::new(), 1.0), None);
    }

    #[test]
    fn an_old_log_that_does_not_grow_is_not_taken_for_a_live_one() {
        use rigd_sim::xl80::{write_log, LogFormat, Xl80Params};
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("old.csv");
        let an_hour_ago = SystemTime::now() - Duration::from_secs(3600);
        let readings: Vec<f64> = (0..500).map(|i| i as f64).collect();
        write_log(
            &path,
            LogFormat::Csv,
            &Xl80Params::default(),
            an_hour_ago,
            &readings,
        )
        .unwrap();
        let f = Follower::new(&path, crate::xl80::Xl80Format::Csv);
        let mut log = FollowedLog::new(f, Duration::from_millis(1));
        log.begin(SystemTime::now());
        // No growth seen: the date is taken as written, so nothing covers now...
        assert_eq!(log.position_at(SystemTime::now()), None);
        let src = log.source();
        assert_eq!(src.log_minus_pc_s, 0.0);
        assert!(src.clock.contains("as written"), "{}", src.clock);
        // ...no sample is handed to the session as the job's...
        assert!(log.take_samples().is_empty());
        // ...but its own times still place its readings: 100 Hz from its whole-second date.
        let secs = an_hour_ago
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_secs();
        let at = std::time::UNIX_EPOCH + Duration::from_secs(secs) + Duration::from_millis(4_505);
        let x = log.position_at(at).unwrap();
        assert!((x - 450.5).abs() < 1.0, "{x}");
    }

    #[test]
    fn a_bound_found_while_a_job_records_waits_for_the_jobs_end() {
        let f = Follower::new(
            Path::new("/nonexistent/xl80.csv"),
            crate::xl80::Xl80Format::Csv,
        );
        let mut log = FollowedLog::new(f, Duration::from_millis(1));
        log.bound_offset(-0.010);
        assert_eq!(log.log_minus_pc_s(), -0.010);
        log.recording = true;
        log.recent.push_back(s(100.0, 1.0));
        log.bound_offset(-0.008);
        // Held: the recorded samples keep one clock for the job.
        assert_eq!(log.log_minus_pc_s(), -0.010);
        assert_eq!(log.recent[0].t_unix_s, 100.0);
        log.end();
        assert_eq!(log.log_minus_pc_s(), -0.008);
        assert!((log.recent[0].t_unix_s - 99.998).abs() < 1e-9);
    }
}
