//! A recorded session as a rig. The stage reports the recorded axis positions, the camera
//! yields the recorded frames and the interferometer the recorded readings, in the order the
//! job recorded them, so a replayed job gets the same result (or another, with other
//! processing settings: `daemon::replay`).

use super::{Rig, RigInfo, RigMode};
use crate::hw::devices::{
    Camera, Frame, HwError, LogSample, LogSource, MotionState, PositionLog, Stage, StageMachine,
    StageStatus,
};
use crate::session::{Session, SessionError, StepRow, INTERFEROMETER};
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// Build the replay rig for `session` (fails on an unreadable `interferometer.csv`).
pub fn replay(session: &Session) -> Result<Rig, SessionError> {
    let rows = Arc::new(Mutex::new(VecDeque::from(session.steps.clone())));
    let mut info: RigInfo = session.manifest.rig.clone();
    info.mode = RigMode::Replay;
    // The recorded readings stand in for the interferometer.
    info.interferometer = true;
    let stage = |follows: bool| -> Box<dyn Stage> {
        Box::new(ReplayStage {
            rows: session.steps.clone().into(),
            position_um: 0.0,
            follows,
            // The axis registers as it did live: where its motor really went.
            machine: (!follows)
                .then(|| session.manifest.rig.axis_machine.clone())
                .flatten(),
        })
    };
    // A plan that moved the piezo besides the axis moved it only when its target changed:
    // its replay goes where it is told (the job registers the piezo by its commands).
    let piezo_follows = session.manifest.job.stages().1;
    Ok(Rig {
        info,
        axis: stage(false),
        piezo: Some(stage(piezo_follows)),
        camera: Box::new(ReplayCamera {
            session: session.clone(),
            rows: rows.clone(),
            size: session.manifest.rig.frame_size,
        }),
        log: Some(Box::new(ReplayLog::new(session)?)),
    })
}

/// Reports the recorded axis position of each step in turn.
struct ReplayStage {
    rows: VecDeque<StepRow>,
    position_um: f64,
    /// Goes where it is told instead (the piezo of a 2-D plan).
    follows: bool,
    /// The recorded controller's motion settings.
    machine: Option<StageMachine>,
}

impl Stage for ReplayStage {
    fn name(&self) -> &str {
        "replay-stage"
    }
    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError> {
        self.move_abs(self.position_um + delta_um)
    }
    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        if self.follows {
            self.position_um = target_um;
            return Ok(());
        }
        let row = self.rows.pop_front().ok_or_else(|| HwError::Other {
            device: "replay-stage".into(),
            message: format!("no recorded step left for a move to {target_um} µm"),
        })?;
        self.position_um = row.axis_um;
        Ok(())
    }
    fn wait_settled(&mut self, _timeout: Duration) -> Result<f64, HwError> {
        Ok(self.position_um)
    }
    fn position_um(&mut self) -> Result<f64, HwError> {
        Ok(self.position_um)
    }
    fn stop(&mut self) -> Result<(), HwError> {
        Ok(())
    }
    fn home(&mut self) -> Result<(), HwError> {
        Ok(())
    }
    fn status(&mut self) -> Result<StageStatus, HwError> {
        Ok(StageStatus {
            state: MotionState::Idle,
            position_um: self.position_um,
        })
    }
    fn machine(&self) -> Option<StageMachine> {
        self.machine.clone()
    }
}

/// Yields the recorded frames in order, with their recorded timestamps and sequences.
struct ReplayCamera {
    session: Session,
    rows: Arc<Mutex<VecDeque<StepRow>>>,
    size: (u32, u32),
}

impl ReplayCamera {
    fn next(&mut self) -> Result<Frame, HwError> {
        let err = |message: String| HwError::Other {
            device: "replay-camera".into(),
            message,
        };
        let row = self
            .rows
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .pop_front()
            .ok_or_else(|| err("no recorded frame left".into()))?;
        // Never through a symlink planted in the session: the frame must be the session's
        // (or, for a replay's replay, the recorded session's its manifest names).
        let (dir, rel) = self
            .session
            .frame_file(row.index)
            .map_err(|e| err(e.to_string()))?;
        let path = dir.join(&rel);
        let max = crate::bounds::MAX_FRAME_BYTES;
        let bytes =
            crate::nofollow::read_in_max(&dir, &rel, max).map_err(|e| err(e.to_string()))?;
        // The recorded frame size, checked from the header before a pixel is decoded.
        let image = crate::bounds::decode_frame(&bytes, Some(self.size))
            .map_err(|e| err(format!("{}: {e}", path.display())))?;
        let timestamp = Duration::try_from_secs_f64(row.t_unix_s)
            .ok()
            .and_then(|d| UNIX_EPOCH.checked_add(d))
            .ok_or_else(|| {
                err(format!(
                    "frame {}: t_unix_s {} is not a time",
                    row.index, row.t_unix_s
                ))
            })?;
        Ok(Frame {
            image,
            sequence: row.sequence,
            timestamp,
        })
    }
}

impl Camera for ReplayCamera {
    fn name(&self) -> &str {
        "replay-camera"
    }
    fn size(&self) -> (u32, u32) {
        self.size
    }
    fn grab(&mut self, _timeout: Duration) -> Result<Frame, HwError> {
        self.next()
    }
    fn grab_fresh(&mut self, _nb: SystemTime, _timeout: Duration) -> Result<Frame, HwError> {
        self.next()
    }
}

/// The recorded interferometer: each frame gets the reading the live job recorded for it
/// (so `registration: interferometer` replays exactly), and the replay session gets the
/// recorded samples of `interferometer.csv` as far as its frames reach.
struct ReplayLog {
    rows: Vec<StepRow>,
    samples: VecDeque<LogSample>,
    taken: Vec<LogSample>,
    source: LogSource,
}

impl ReplayLog {
    fn new(session: &Session) -> Result<ReplayLog, SessionError> {
        let source = match &session.manifest.interferometer {
            Some(s) => LogSource {
                replayed_from: Some(session.manifest.name.clone()),
                ..s.clone()
            },
            None => LogSource {
                path: session.dir.join(INTERFEROMETER).display().to_string(),
                format: "rigd-session".into(),
                replayed_from: Some(session.manifest.name.clone()),
                ..LogSource::default()
            },
        };
        Ok(ReplayLog {
            rows: session.steps.clone(),
            samples: session.interferometer_samples()?.into(),
            taken: Vec::new(),
            source,
        })
    }
}

impl PositionLog for ReplayLog {
    fn begin(&mut self, _from: SystemTime) {}

    fn position_at(&mut self, t: SystemTime) -> Option<f64> {
        let t = crate::timestamps::unix_s(t);
        // Hand on the samples up to the first one at or after the frame, as the live job
        // had read them.
        while let Some(s) = self.samples.pop_front() {
            self.taken.push(s);
            if s.t_unix_s >= t {
                break;
            }
        }
        self.rows
            .iter()
            .min_by(|a, b| (a.t_unix_s - t).abs().total_cmp(&(b.t_unix_s - t).abs()))
            .and_then(|r| r.interferometer_um)
    }

    fn take_samples(&mut self) -> Vec<LogSample> {
        std::mem::take(&mut self.taken)
    }

    fn source(&self) -> LogSource {
        self.source.clone()
    }
}
