//! The interferometer as a job sees it: the XL-80's log file, followed while the laser
//! software writes it. One implementation for both rigs — `rigd --config` follows `[xl80]
//! path`, `rigd --sim` follows the file its simulated XL-80 writes live — so every sim job
//! runs the hardware path.
//!
//! Per frame the runner asks for the reading at the frame's exposure time; the log is
//! polled until it holds a sample at or after that time (or a deadline passes), and the
//! reading is interpolated linearly between the two samples around it. Every sample read
//! from the job's start on is handed to the session (`interferometer.csv`).
//!
//! Sample times are the log's start date plus the sample's time, minus `log_minus_pc_s`
//! (the log clock minus the PC clock; 0 when the laser software runs on the rig PC and its
//! capture date is exact). No offset is estimated: the formats' dates have whole seconds,
//! so a capture started mid-second is up to 1 s early on the PC clock (docs/xl80.md).

use crate::daemon::rig::{LogSample, LogSource, PositionLog};
use crate::daemon::session::{unix_s, SessionError, SessionWriter};
use crate::hw::HwError;
use crate::xl80::{Follower, Xl80Format};
use rigd_sim::xl80::{LiveOptions, LogFormat};
use rigd_sim::SimRig;
use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant, SystemTime};

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
    log_minus_pc_s: f64,
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
    /// A temporary log file this follower owns (the sim's), removed on drop.
    owned_file: Option<PathBuf>,
}

impl Drop for FollowedLog {
    fn drop(&mut self) {
        if let Some(p) = &self.owned_file {
            let _ = std::fs::remove_file(p);
        }
    }
}

impl FollowedLog {
    /// Follow `follower`'s file, polling every `poll` while waiting for a frame's sample.
    pub fn new(follower: Follower, poll: Duration) -> FollowedLog {
        let poll = poll.max(Duration::from_millis(1));
        FollowedLog {
            follower,
            poll,
            max_wait: (poll * 5).max(Duration::from_secs(1)),
            log_minus_pc_s: 0.0,
            recent: VecDeque::new(),
            pending: Vec::new(),
            from_unix_s: f64::INFINITY,
            stalled: false,
            untimed: 0,
            last_error: None,
            owned_file: None,
        }
    }

    /// The log's clock minus the PC's, seconds (default 0).
    pub fn with_log_minus_pc_s(mut self, s: f64) -> FollowedLog {
        self.log_minus_pc_s = s;
        self
    }

    /// Read what the file gained; true if it gained samples.
    fn catch_up(&mut self) -> bool {
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
                t_unix_s: unix_s(at) - self.log_minus_pc_s,
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

/// How often the daemon polls the sim's log while waiting for a frame's sample.
const SIM_POLL: Duration = Duration::from_millis(2);

/// The simulated XL-80 of `rig` run the way the real one runs: it writes its live log (CSV
/// or RTX) to `path` — a temporary file when `None`, removed with the returned log — and
/// the daemon follows that file like a real rig's. The capture is dated on a whole second
/// and flushed after every sample, so the log's clock is the PC's.
pub fn sim_log(
    rig: &mut SimRig,
    path: Option<PathBuf>,
    format: Xl80Format,
    rtx_um_per_unit: f64,
) -> Result<FollowedLog, HwError> {
    static N: AtomicU32 = AtomicU32::new(0);
    let (path, owned) = match path {
        Some(p) => (p, false),
        None => {
            let n = N.fetch_add(1, Ordering::Relaxed);
            let ext = if format == Xl80Format::Rtx {
                "rtx"
            } else {
                "csv"
            };
            let name = format!("rigd-sim-xl80-{}-{n}.{ext}", std::process::id());
            (std::env::temp_dir().join(name), true)
        }
    };
    let opts = LiveOptions {
        flush_period: Duration::ZERO,
        start_on_whole_second: true,
    };
    let sim_format = match format {
        Xl80Format::Csv => LogFormat::Csv,
        Xl80Format::Rtx => LogFormat::Rtx,
    };
    rig.start_xl80_log_with(&path, sim_format, opts)
        .map_err(|e| HwError::Other {
            device: "sim-xl80".into(),
            message: e.to_string(),
        })?;
    let follower = Follower::new(&path, format).with_rtx_unit_um(rtx_um_per_unit);
    let mut log = FollowedLog::new(follower, SIM_POLL);
    if owned {
        log.owned_file = Some(path);
    }
    Ok(log)
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
        self.from_unix_s = unix_s(from);
        self.pending.clear();
        self.catch_up();
        let from = self.from_unix_s;
        self.pending.retain(|s| s.t_unix_s >= from);
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

    fn source(&self) -> LogSource {
        let log = self.follower.log();
        LogSource {
            path: self.follower.path().display().to_string(),
            format: format!("{:?}", log.format).to_lowercase(),
            um_per_unit: log.um_per_unit,
            sample_rate_hz: log.sample_rate_hz,
            date: log.meta.date.clone(),
            log_minus_pc_s: self.log_minus_pc_s,
            fields: log.meta.fields.clone(),
            garbled: log.garbled.count,
            replayed_from: None,
        }
    }
}

/// At a job's start: point the log at the job and record its source in the session.
pub fn begin_job(
    log: Option<&mut (dyn PositionLog + 'static)>,
    session: &mut SessionWriter,
) -> Result<(), SessionError> {
    match log {
        Some(log) => {
            log.begin(SystemTime::now());
            session.begin_interferometer(log.source())
        }
        None => Ok(()),
    }
}

/// For a captured frame: the reading at its time, after the samples read so far are on disk.
pub fn at_frame(
    log: Option<&mut (dyn PositionLog + 'static)>,
    session: &mut SessionWriter,
    t: SystemTime,
) -> Result<Option<f64>, SessionError> {
    let Some(log) = log else {
        return Ok(None);
    };
    let at = log.position_at(t);
    session.append_interferometer(&log.take_samples())?;
    Ok(at)
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
