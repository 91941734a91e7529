//! The step engine: runs a plan on the devices, one step at a time (move, wait for the
//! move while watching for a stop, settle, grab a fresh frame), and hands one
//! [`StepRecord`] per step to its sink. The interferometer is read behind it
//! (`acquisition::interferometer`). Blocking code on its own thread; it
//! knows nothing of sessions, events or the wire.
//!
//! Stops: a cancel is seen mid-move (the stage is stopped where it is: GRBL feed hold, GCS
//! HLT); a shutdown lets the move end. Either, arriving during the settle or the grab, ends
//! the step without a frame; arriving after the last step, the job still ends cancelled.
//!
//! A resumed plan (`Plan::first_index`) starts at its first missing frame: the first move
//! goes there from wherever the stage is (checked by the driver against `max_step_um`, as
//! any job's first move), and the plan goes on as if never interrupted.
//!
//! Pauses (`acquisition::pause`): a client's is taken between steps, a controller's feed
//! hold mid-move (or fails the step, as `on_feed_hold` says); either waits for a resume or
//! a stop, and the plan goes on with the frame it was at.

use crate::acquisition::outcome::{JobError, Outcome, Phase, Stop, StopCause, StoppedAt};
use crate::acquisition::pause::{HoldPolicy, Pause, PauseCause, PauseEvent};
use crate::acquisition::plan::{Plan, RunPlan};
use crate::acquisition::record::{ms, StepRecord, StepTimings};
use crate::acquisition::sink::{SinkError, StepSink};
use crate::hw::{Camera, HwError, MotionState, Stage};
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

/// A job's stop request, set by clients and signals, read by the engine; and its pause
/// switch.
#[derive(Debug, Default)]
pub struct StopFlag {
    stop: AtomicU8,
    pub pause: Pause,
}

const RUN: u8 = 0;
const CANCEL: u8 = 1;
const SHUTDOWN: u8 = 2;

impl StopFlag {
    pub fn cancel(&self) {
        self.stop.store(CANCEL, Ordering::SeqCst);
    }
    /// The daemon stops; a client's cancel asked for earlier is kept.
    pub fn shutdown(&self) {
        let _ = self
            .stop
            .compare_exchange(RUN, SHUTDOWN, Ordering::SeqCst, Ordering::SeqCst);
    }
    pub fn cause(&self) -> Option<StopCause> {
        match self.stop.load(Ordering::SeqCst) {
            RUN => None,
            CANCEL => Some(StopCause::Client),
            _ => Some(StopCause::Shutdown),
        }
    }
}

/// The devices one job drives.
pub struct Devices<'a> {
    /// The stage of the plan's `positions_um`.
    pub stage: &'a mut dyn Stage,
    pub camera: &'a mut dyn Camera,
    /// The piezo, for a plan that moves it besides the axis (`RunPlan::piezo_um`).
    pub piezo: Option<&'a mut dyn Stage>,
}

/// How the engine steps.
#[derive(Debug, Clone)]
pub struct EngineSettings {
    pub settle: Duration,
    /// How long a grab may wait for a fresh frame ([camera] frame_timeout_ms).
    pub grab_timeout: Duration,
    /// How long a move may take.
    pub move_timeout: Duration,
    /// Between status polls of a moving stage: how late a cancel stops it, at most.
    pub move_poll: Duration,
    /// Each repeat starts this long after the previous one started (`interval_s`).
    pub repeat_interval: Option<Duration>,
    /// A feed hold mid-move pauses the job or fails it (`[daemon] on_feed_hold`).
    pub on_feed_hold: HoldPolicy,
}

impl Default for EngineSettings {
    fn default() -> Self {
        EngineSettings {
            settle: Duration::from_millis(20),
            grab_timeout: Duration::from_secs(5),
            move_timeout: Duration::from_secs(30),
            move_poll: Duration::from_millis(2),
            repeat_interval: None,
            on_feed_hold: HoldPolicy::Pause,
        }
    }
}

/// Why a step produced no frame.
enum StepEnd {
    Hw(HwError),
    Stopped(Stop),
}

impl From<HwError> for StepEnd {
    fn from(e: HwError) -> StepEnd {
        StepEnd::Hw(e)
    }
}

pub struct Engine<'a> {
    pub plan: &'a Plan,
    pub settings: EngineSettings,
    pub stop: &'a StopFlag,
}

impl Engine<'_> {
    /// Run the plan; the sink is flushed (`finish`) whatever the outcome. On any fault or
    /// stop the stage is stopped before this returns.
    pub fn run(&self, dev: &mut Devices<'_>, sink: &mut dyn StepSink) -> Outcome {
        // A panic below (a device, a sink) fails the job, the stages stopped; the sinks are
        // still flushed, so the session closes with what was recorded.
        let caught =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.capture(dev, sink)));
        let outcome = caught.unwrap_or_else(|panic| {
            let message = crate::text::panic_message(panic.as_ref());
            tracing::error!(panic = %message, "the step engine panicked: the job fails");
            let e = JobError::Internal {
                message: format!("the step engine panicked: {message}"),
                stopped: None,
            };
            self.failed(dev, e)
        });
        match (outcome, sink.finish()) {
            (Outcome::Finished, Err(e)) => Outcome::Failed(sink_error(e)),
            (Outcome::Cancelled(s), Err(e)) => {
                Outcome::Failed(sink_error(e).after(Some(s.to_string())))
            }
            (o, _) => o,
        }
    }

    fn capture(&self, dev: &mut Devices<'_>, sink: &mut dyn StepSink) -> Outcome {
        let total = self.plan.total_frames;
        let mut index = 0u32;
        let mut repeat_started: Option<(u32, Instant)> = None;
        // The piezo is moved only when its target changes (once a row in a grid).
        let mut piezo_at: Option<f64> = None;
        // Where the last frame was taken: where a pause between steps leaves the stage.
        let mut last_um = None;
        // A resumed plan starts at its first missing frame: the frames before it (whole
        // runs, and the start of the run it falls in) are the original session's.
        let first = self.plan.first_index;
        for run in &self.plan.runs {
            let len = run.positions_um.len() as u32;
            if index + len <= first {
                index += len;
                continue;
            }
            if let Err(cause) = self.wait_for_repeat(run.repeat, &mut repeat_started) {
                return self.stopped(dev, cause, None);
            }
            for (i, &commanded_um) in run.positions_um.iter().enumerate() {
                if index < first {
                    index += 1;
                    continue;
                }
                if let Some(cause) = self.stop.cause() {
                    return self.stopped(dev, cause, None);
                }
                if let Err(cause) = self.pause_between_steps(index, last_um, dev, sink) {
                    return self.stopped(dev, cause, None);
                }
                let piezo = run
                    .piezo_um
                    .as_ref()
                    .map(|p| (p[i], piezo_at != Some(p[i])));
                piezo_at = piezo.map(|p| p.0);
                let rec = match self.step(dev, run, index, (commanded_um, piezo), total) {
                    Ok(r) => r,
                    Err(StepEnd::Stopped(s)) => return self.stopped(dev, s.cause, s.during),
                    Err(StepEnd::Hw(source)) => {
                        let stopped = stop_devices(dev);
                        return Outcome::Failed(JobError::Hardware { source, stopped });
                    }
                };
                last_um = Some(rec.axis_um);
                if let Err(e) = sink.step(Arc::new(rec)) {
                    return self.failed(dev, sink_error(e));
                }
                index += 1;
            }
            if let Err(e) = sink.end_run(run.run) {
                return self.failed(dev, sink_error(e));
            }
        }
        // A stop that came during the last step still ends the job as it was told.
        match self.stop.cause() {
            Some(cause) => self.stopped(dev, cause, None),
            None => Outcome::Finished,
        }
    }

    /// A client's pause, taken here between steps: the stage is idle where the last frame
    /// was taken; the next step moves and settles as any step does.
    /// A client's pause, taken here between steps. Meanwhile the camera serves whoever
    /// watches it (the live view, through the sink): a pause is when focus is checked.
    fn pause_between_steps(
        &self,
        index: u32,
        last_um: Option<f64>,
        dev: &mut Devices<'_>,
        sink: &mut dyn StepSink,
    ) -> Result<(), StopCause> {
        if !self.stop.pause.take_request() {
            return Ok(());
        }
        let event = PauseEvent::Paused {
            next_index: index,
            at_um: last_um,
            cause: PauseCause::Client,
        };
        let timeout = self.settings.grab_timeout;
        let serve = || {
            if sink.wants_paused_frame() {
                let frame = dev.camera.grab_fresh(SystemTime::now(), timeout);
                let at = dev.stage.position_um().ok();
                sink.paused_frame(frame, at);
            }
        };
        self.stop
            .pause
            .hold_until_resumed_with(event, || self.stop.cause(), serve)
    }

    fn stopped(
        &self,
        dev: &mut Devices<'_>,
        cause: StopCause,
        during: Option<(Phase, f64)>,
    ) -> Outcome {
        let stopped = stop_devices(dev);
        Outcome::Cancelled(Stop {
            cause,
            during,
            stopped,
        })
    }

    fn failed(&self, dev: &mut Devices<'_>, e: JobError) -> Outcome {
        Outcome::Failed(e.with_stopped(stop_devices(dev)))
    }

    /// Before a run of a new repeat: wait until `interval` after the previous repeat
    /// started (in short sleeps: a stop ends the wait). `Err`: stopped while waiting.
    fn wait_for_repeat(
        &self,
        repeat: u32,
        started: &mut Option<(u32, Instant)>,
    ) -> Result<(), StopCause> {
        let due = match *started {
            Some((r, _)) if r == repeat => return Ok(()),
            Some((_, t)) => self.settings.repeat_interval.map(|i| t + i),
            None => None,
        };
        while let Some(left) = due.map(|d| d.saturating_duration_since(Instant::now())) {
            if let Some(cause) = self.stop.cause() {
                return Err(cause);
            }
            if left.is_zero() {
                break;
            }
            std::thread::sleep(left.min(Duration::from_millis(20)));
        }
        *started = Some((repeat, Instant::now()));
        Ok(())
    }

    /// Move (the stage, and the piezo to `piezo`'s target if it is to move: both settled
    /// before the grab), settle, grab one fresh frame.
    fn step(
        &self,
        dev: &mut Devices<'_>,
        run: &RunPlan,
        index: u32,
        (commanded_um, piezo): (f64, Option<(f64, bool)>),
        total_frames: u32,
    ) -> Result<StepRecord, StepEnd> {
        let t0 = Instant::now();
        let piezo_stage = match (piezo, dev.piezo.as_deref_mut()) {
            (Some(_), None) => return Err(StepEnd::Hw(no_piezo())),
            (Some((target, true)), Some(p)) => {
                p.move_abs(target)?;
                Some((target, Some(p)))
            }
            (Some((target, false)), Some(_)) => Some((target, None)),
            (None, _) => None,
        };
        dev.stage.move_abs(commanded_um)?;
        let axis_um = self.finish_move(dev.stage, commanded_um, index)?;
        let (piezo_commanded_um, piezo_um) = match piezo_stage {
            Some((target, Some(p))) => (Some(target), Some(self.finish_move(p, target, index)?)),
            // Not moved since the previous frame: where it settled then.
            Some((target, None)) => (Some(target), Some(self.last_piezo_um(dev, target))),
            None => (None, None),
        };
        let t1 = Instant::now();
        self.settle(commanded_um)?;
        let t2 = Instant::now();
        let frame = dev
            .camera
            .grab_fresh(SystemTime::now(), self.settings.grab_timeout)?;
        let t3 = Instant::now();
        if let Some(cause) = self.stop.cause() {
            // The frame may show the stage stopping: not a good frame.
            return Err(StepEnd::Stopped(Stop {
                cause,
                during: Some((Phase::Grab, commanded_um)),
                stopped: None,
            }));
        }
        Ok(StepRecord {
            index,
            run: run.run,
            case: run.case.name.clone(),
            repeat: run.repeat,
            commanded_um,
            axis_um,
            interferometer_um: None,
            // Where the motor really went, when its steps are coarser than the command.
            registration_um: dev
                .stage
                .machine()
                .map_or(commanded_um, |m| m.reached_um(commanded_um, axis_um)),
            piezo_commanded_um,
            piezo_um,
            samples: Vec::new(),
            log_source: None,
            frame,
            timings: StepTimings {
                move_ms: ms(t1 - t0),
                settle_ms: ms(t2 - t1),
                grab_ms: ms(t3 - t2),
            },
            total_frames,
        })
    }

    /// The piezo's position when it was not moved for this frame: its status (the target,
    /// if the status cannot be read: the step does not fail on a stage it did not move).
    fn last_piezo_um(&self, dev: &mut Devices<'_>, target_um: f64) -> f64 {
        dev.piezo
            .as_deref_mut()
            .and_then(|p| p.status().ok())
            .map_or(target_um, |s| s.position_um)
    }

    /// Wait out the settle time in short sleeps, so a stop is not held up by it.
    fn settle(&self, commanded_um: f64) -> Result<(), StepEnd> {
        let t = Instant::now();
        let settle = self.settings.settle;
        loop {
            if let Some(cause) = self.stop.cause() {
                return Err(StepEnd::Stopped(Stop {
                    cause,
                    during: Some((Phase::Settle, commanded_um)),
                    stopped: None,
                }));
            }
            let left = settle.saturating_sub(t.elapsed());
            if left.is_zero() {
                return Ok(());
            }
            std::thread::sleep(left.min(Duration::from_millis(20)));
        }
    }

    /// Wait for the move to `target_um` just commanded to finish, watching for a cancel
    /// while the stage reports it moving. Returns the settled position.
    ///
    /// A stage that stops moving in `Holding` (feed hold or safety door: never rigd's doing
    /// here) or in `Alarm` fails the step at once, naming the state and where the stage is,
    /// rather than waiting out the deadline for a move that will not finish by itself.
    fn finish_move(
        &self,
        stage: &mut dyn Stage,
        target_um: f64,
        index: u32,
    ) -> Result<f64, StepEnd> {
        // A long move at the controller's own rate gets its planned time on top.
        let budget = self.settings.move_timeout + stage.planned_move().unwrap_or_default();
        let mut deadline = Instant::now() + budget;
        loop {
            if self.stop.cause() == Some(StopCause::Client) {
                return Err(StepEnd::Stopped(Stop {
                    cause: StopCause::Client,
                    during: Some((Phase::Move, target_um)),
                    stopped: None,
                }));
            }
            let st = stage.status()?;
            match st.state {
                MotionState::Moving | MotionState::Homing => {}
                MotionState::Idle => break,
                MotionState::Holding if self.settings.on_feed_hold == HoldPolicy::Fail => {
                    return Err(held(stage.name(), st.position_um, target_um))
                }
                MotionState::Holding => {
                    self.pause_on_hold(stage, st.position_um, target_um, index)?;
                    // The pause does not count against the move's deadline.
                    deadline = Instant::now() + budget;
                    continue;
                }
                MotionState::Alarm => return Err(alarm(stage, st.position_um, target_um)),
            }
            if Instant::now() >= deadline {
                return Err(StepEnd::Hw(HwError::NotSettled {
                    device: stage.name().into(),
                    timeout_ms: budget.as_millis() as u64,
                    state: format!("still {} at {:.1} µm", st.state, st.position_um),
                }));
            }
            std::thread::sleep(self.settings.move_poll);
        }
        // The driver's own wait confirms the end of the move (and reports alarms and timeouts).
        let left = deadline.saturating_duration_since(Instant::now());
        Ok(stage.wait_settled(left.max(Duration::from_millis(1)))?)
    }
}

impl Engine<'_> {
    /// The controller holds mid-move: pause the job there; on resume, resume the
    /// controller and issue the interrupted move again (a no-op if the controller already
    /// went on with it), then wait for it as before.
    fn pause_on_hold(
        &self,
        stage: &mut dyn Stage,
        at_um: f64,
        target_um: f64,
        index: u32,
    ) -> Result<(), StepEnd> {
        let event = PauseEvent::Paused {
            next_index: index,
            at_um: Some(at_um),
            cause: PauseCause::FeedHold {
                device: stage.name().to_string(),
                target_um,
            },
        };
        let stopped = |cause| {
            StepEnd::Stopped(Stop {
                cause,
                during: Some((Phase::Move, target_um)),
                stopped: None,
            })
        };
        self.stop
            .pause
            .hold_until_resumed(event, || self.stop.cause())
            .map_err(stopped)?;
        stage.resume()?;
        stage.move_abs(target_um)?;
        Ok(())
    }
}

fn held(device: &str, at_um: f64, target_um: f64) -> StepEnd {
    StepEnd::Hw(HwError::Other {
        device: device.into(),
        message: format!(
            "feed hold at {at_um:.1} µm during the move to {target_um} µm (the controller \
             holds: feed hold or safety door, not asked for by rigd)"
        ),
    })
}

/// The driver names the alarm (its code and meaning) if it knows it.
fn alarm(stage: &mut dyn Stage, at_um: f64, target_um: f64) -> StepEnd {
    StepEnd::Hw(match stage.wait_settled(Duration::from_millis(1)) {
        Err(e @ HwError::Alarm { .. }) => e,
        _ => HwError::Other {
            device: stage.name().into(),
            message: format!("alarm at {at_um:.1} µm during the move to {target_um} µm"),
        },
    })
}

fn no_piezo() -> HwError {
    HwError::Other {
        device: "piezo".into(),
        message: "the plan moves the piezo, and this rig has none".into(),
    }
}

/// Stop the job's stages (the piezo too, if it has one) and say where the stage was left.
fn stop_devices(dev: &mut Devices<'_>) -> Option<StoppedAt> {
    if let Some(p) = dev.piezo.as_deref_mut() {
        if let Err(e) = p.stop() {
            tracing::warn!(stage = p.name(), "stopping after the job: {e}");
        }
    }
    stop_stage(dev.stage)
}

/// Stop the stage and say where it was left.
pub fn stop_stage(stage: &mut dyn Stage) -> Option<StoppedAt> {
    let stop_error = stage.stop().err().map(|e| {
        tracing::warn!(stage = stage.name(), "stopping after the job: {e}");
        e.to_string()
    });
    let (position_um, state, status_error) = match stage.status() {
        Ok(st) => (Some(st.position_um), Some(st.state), None),
        Err(e) => (None, None, Some(e.to_string())),
    };
    Some(StoppedAt {
        device: stage.name().to_string(),
        position_um,
        state,
        stop_error,
        status_error,
    })
}

/// A sink's failure as the job's.
pub fn sink_error(e: SinkError) -> JobError {
    match e {
        SinkError::Disk {
            file,
            disk_full,
            message,
        } => JobError::Disk {
            file,
            disk_full,
            message,
            stopped: None,
            earlier: None,
        },
        SinkError::NoInterferometerReading { index } => JobError::NoInterferometerReading {
            index,
            stopped: None,
        },
        SinkError::Panicked { sink, message } => JobError::Processing {
            message: format!("{sink}: {message}"),
            stopped: None,
        },
    }
}
