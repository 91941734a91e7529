//! The sim rig's XL-80, run the way the real one runs: a live capture written to a file by
//! the simulated laser (`rigd_sim::xl80::LiveLog`, from the line of sight's true position
//! with the laser's noise), followed by the daemon with the hardware rig's code
//! ([`FollowedLog`]). A new capture is started for every job, as an operator starts one per
//! test, and finished when the job ends, so the file holds one job and does not grow while
//! the daemon idles (it grew ~24 kB/s at 1 kHz before).

use crate::hw::devices::{HwError, LogSample, LogSource, PositionLog};
use crate::rig::FollowedLog;
use crate::xl80::{Follower, Xl80Format};
use rigd_sim::motion::TruePosition;
use rigd_sim::xl80::{LengthUnit, LiveLog, LiveOptions, LogFormat, Xl80, Xl80Params};
use rigd_sim::SimRig;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime};

/// The sim laser's sample rate in the daemon's rigs. The XL-80 captures at up to 50 kHz; at
/// 1 kHz the samples around a frame are at most 1 ms from it, so a frame grabbed right after
/// a move ends is not read from a sample taken while the axis still moved.
pub const SIM_RATE_HZ: f64 = 1000.0;
/// How often the daemon polls the sim's log while waiting for a frame's sample.
const SIM_POLL: Duration = Duration::from_millis(1);

/// The simulated XL-80 and the daemon's follower of its log.
pub struct SimXl80 {
    source: Arc<dyn TruePosition>,
    params: Xl80Params,
    format: Xl80Format,
    rtx_um_per_unit: f64,
    path: PathBuf,
    /// A temporary file of ours (removed when done), not a configured path.
    owned: bool,
    live: Option<LiveLog>,
    log: FollowedLog,
    /// The laser read once on request between jobs (`position`), with the log's noise,
    /// datum and beam direction: the idle log does not grow.
    one_shot: Xl80,
}

impl SimXl80 {
    /// The XL-80 of `rig`, writing `path` (a temporary file when `None`) in `format`.
    pub fn new(
        rig: &SimRig,
        path: Option<PathBuf>,
        format: Xl80Format,
        rtx_um_per_unit: f64,
    ) -> Result<SimXl80, HwError> {
        static N: AtomicU32 = AtomicU32::new(0);
        let (path, owned) = match path {
            Some(p) => (p, false),
            None => {
                sweep_dead_logs(&std::env::temp_dir());
                let n = N.fetch_add(1, Ordering::Relaxed);
                let ext = match format {
                    Xl80Format::Csv => "csv",
                    Xl80Format::Rtx => "rtx",
                };
                let name = format!("{PREFIX}{}-{n}.{ext}", std::process::id());
                (std::env::temp_dir().join(name), true)
            }
        };
        let params = Xl80Params {
            sample_rate_hz: SIM_RATE_HZ,
            // Write the `.rtx` in the unit the follower is told it is in.
            rtx_unit: if rtx_um_per_unit == 1.0 {
                LengthUnit::Um
            } else {
                LengthUnit::Mm
            },
            ..rig.config().xl80.clone()
        };
        params.validate().map_err(|e| sim_error(e.to_string()))?;
        let log = FollowedLog::new(Follower::new(&path, format), SIM_POLL);
        let one_shot = Xl80::new(params.clone()).map_err(|e| sim_error(e.to_string()))?;
        let mut x = SimXl80 {
            one_shot,
            source: Arc::clone(&rig.line_of_sight) as Arc<dyn TruePosition>,
            params,
            format,
            rtx_um_per_unit,
            path,
            owned,
            live: None,
            log,
        };
        // Check the file can be written now, not at the first job; then stop: the laser
        // logs only while a job runs, so the file does not grow while the daemon idles.
        x.restart()?;
        x.stop_capture()?;
        Ok(x)
    }

    /// Finish the running capture, if any: the file is complete and stops growing.
    fn stop_capture(&mut self) -> Result<(), HwError> {
        match self.live.take() {
            Some(l) => l.finish().map(drop).map_err(|e| sim_error(e.to_string())),
            None => Ok(()),
        }
    }

    /// Finish the running capture and start a new one in a fresh file.
    fn restart(&mut self) -> Result<(), HwError> {
        if let Some(l) = self.live.take() {
            l.finish().map_err(|e| sim_error(e.to_string()))?;
        }
        match std::fs::remove_file(&self.path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(sim_error(format!("{}: {e}", self.path.display())))
            }
            _ => {}
        }
        let format = match self.format {
            Xl80Format::Csv => LogFormat::Csv,
            Xl80Format::Rtx => LogFormat::Rtx,
        };
        let opts = LiveOptions {
            // Every sample is on disk as soon as it is taken.
            flush_period: Duration::ZERO,
            start_on_whole_second: true,
        };
        self.live = Some(
            LiveLog::start_with(
                &self.path,
                format,
                self.params.clone(),
                Arc::clone(&self.source),
                opts,
            )
            .map_err(|e| sim_error(e.to_string()))?,
        );
        let follower =
            Follower::new(&self.path, self.format).with_rtx_unit_um(self.rtx_um_per_unit);
        self.log = FollowedLog::new(follower, SIM_POLL);
        Ok(())
    }
}

const PREFIX: &str = "rigd-sim-xl80-";

/// Remove temporary logs left by daemons that died without dropping their rig (`kill -9`):
/// `rigd-sim-xl80-<pid>-<n>.*` whose process is gone.
fn sweep_dead_logs(dir: &std::path::Path) {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return;
    };
    for e in rd.flatten() {
        let name = e.file_name();
        let Some(pid) = name
            .to_str()
            .and_then(|n| n.strip_prefix(PREFIX))
            .and_then(|rest| rest.split('-').next())
            .and_then(|pid| pid.parse::<u32>().ok())
        else {
            continue;
        };
        if !std::path::Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

fn sim_error(message: String) -> HwError {
    HwError::Other {
        device: "sim-xl80".into(),
        message,
    }
}

impl PositionLog for SimXl80 {
    fn begin(&mut self, from: SystemTime) {
        if let Err(e) = self.restart() {
            tracing::warn!("{e}");
        }
        self.log.begin(from);
    }
    fn position_at(&mut self, t: SystemTime) -> Option<f64> {
        self.log.position_at(t)
    }
    fn take_samples(&mut self) -> Vec<LogSample> {
        self.log.take_samples()
    }
    fn source(&self) -> LogSource {
        self.log.source()
    }
    fn end(&mut self) {
        if let Err(e) = self.stop_capture() {
            tracing::warn!("{e}");
        }
        self.log.end();
    }
    fn reading_now(&mut self) -> Result<LogSample, String> {
        if self.live.is_some() {
            return self.log.reading_now();
        }
        let t = SystemTime::now();
        let los_um = self.source.true_position_um(std::time::Instant::now());
        Ok(LogSample {
            t_unix_s: crate::timestamps::unix_s(t),
            position_um: self.one_shot.read_um(los_um),
            sample: 0,
        })
    }
}

impl Drop for SimXl80 {
    fn drop(&mut self) {
        if let Some(l) = self.live.take() {
            let _ = l.finish();
        }
        if self.owned {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}
