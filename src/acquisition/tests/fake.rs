//! Scripted devices, in the style of embedded-hal-mock: each follows a script of expected
//! calls and their replies, panics naming the call it did not expect, and `done()` checks
//! that the script was used up. They drive the step engine in tests that run in
//! milliseconds: holds, alarms, stops in each phase, stalls, failing stops and polls.

use crate::hw::{Camera, Frame, HwError, MotionState, Stage, StageStatus};
use crate::hw::{LogSample, LogSource, PositionLog};
use image::RgbImage;
use std::collections::VecDeque;
use std::time::{Duration, SystemTime};

/// Something to do when a call is made (set a stop flag, say), after it is checked.
pub type Effect = Box<dyn FnOnce() + Send>;

/// One expected stage call and its reply.
pub enum StageCall {
    MoveAbs(f64, Result<(), HwError>),
    Status(Result<StageStatus, HwError>),
    WaitSettled(Result<f64, HwError>),
    Stop(Result<(), HwError>),
    /// Cycle start after a hold.
    Resume(Result<(), HwError>),
}

pub struct Expect<C> {
    call: C,
    effect: Option<Effect>,
}

impl<C> Expect<C> {
    /// Run `f` when this call is made.
    pub fn then(mut self, f: impl FnOnce() + Send + 'static) -> Expect<C> {
        self.effect = Some(Box::new(f));
        self
    }
    fn take(self) -> C {
        if let Some(f) = self.effect {
            f();
        }
        self.call
    }
}

pub fn move_abs(target_um: f64) -> Expect<StageCall> {
    stage_call(StageCall::MoveAbs(target_um, Ok(())))
}
pub fn move_abs_fails(target_um: f64, e: HwError) -> Expect<StageCall> {
    stage_call(StageCall::MoveAbs(target_um, Err(e)))
}
pub fn status(state: MotionState, position_um: f64) -> Expect<StageCall> {
    stage_call(StageCall::Status(Ok(StageStatus { state, position_um })))
}
pub fn status_fails(e: HwError) -> Expect<StageCall> {
    stage_call(StageCall::Status(Err(e)))
}
pub fn wait_settled(position_um: f64) -> Expect<StageCall> {
    stage_call(StageCall::WaitSettled(Ok(position_um)))
}
pub fn wait_settled_fails(e: HwError) -> Expect<StageCall> {
    stage_call(StageCall::WaitSettled(Err(e)))
}
pub fn stop() -> Expect<StageCall> {
    stage_call(StageCall::Stop(Ok(())))
}
pub fn stop_fails(e: HwError) -> Expect<StageCall> {
    stage_call(StageCall::Stop(Err(e)))
}
pub fn resume() -> Expect<StageCall> {
    stage_call(StageCall::Resume(Ok(())))
}
fn stage_call(call: StageCall) -> Expect<StageCall> {
    Expect { call, effect: None }
}

/// The calls of one uneventful step to `target_um`: move, one poll idle, the settled wait.
pub fn plain_move(target_um: f64) -> Vec<Expect<StageCall>> {
    vec![
        move_abs(target_um),
        status(MotionState::Idle, target_um),
        wait_settled(target_um),
    ]
}

/// A stage that follows a script.
pub struct ScriptedStage {
    name: String,
    script: VecDeque<Expect<StageCall>>,
}

impl ScriptedStage {
    pub fn new(name: &str, script: impl IntoIterator<Item = Expect<StageCall>>) -> ScriptedStage {
        ScriptedStage {
            name: name.into(),
            script: script.into_iter().collect(),
        }
    }

    fn next(&mut self, what: &str) -> StageCall {
        match self.script.pop_front() {
            Some(e) => e.take(),
            None => panic!(
                "{}: unexpected call {what}: the script is used up",
                self.name
            ),
        }
    }

    /// Panics if calls the script expects were not made.
    pub fn done(&self) {
        assert!(
            self.script.is_empty(),
            "{}: {} expected call(s) were not made",
            self.name,
            self.script.len()
        );
    }
}

impl Stage for ScriptedStage {
    fn name(&self) -> &str {
        &self.name
    }
    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError> {
        panic!("{}: unexpected move_rel({delta_um})", self.name)
    }
    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        match self.next(&format!("move_abs({target_um})")) {
            StageCall::MoveAbs(t, r) if t == target_um => r,
            StageCall::MoveAbs(t, _) => panic!(
                "{}: move_abs({target_um}), expected move_abs({t})",
                self.name
            ),
            _ => panic!("{}: unexpected move_abs({target_um})", self.name),
        }
    }
    fn wait_settled(&mut self, _timeout: Duration) -> Result<f64, HwError> {
        match self.next("wait_settled") {
            StageCall::WaitSettled(r) => r,
            _ => panic!("{}: unexpected wait_settled", self.name),
        }
    }
    fn position_um(&mut self) -> Result<f64, HwError> {
        self.status().map(|s| s.position_um)
    }
    fn stop(&mut self) -> Result<(), HwError> {
        match self.next("stop") {
            StageCall::Stop(r) => r,
            _ => panic!("{}: unexpected stop", self.name),
        }
    }
    fn home(&mut self) -> Result<(), HwError> {
        panic!("{}: unexpected home", self.name)
    }
    fn resume(&mut self) -> Result<(), HwError> {
        match self.next("resume") {
            StageCall::Resume(r) => r,
            _ => panic!("{}: unexpected resume", self.name),
        }
    }
    fn status(&mut self) -> Result<StageStatus, HwError> {
        match self.next("status") {
            StageCall::Status(r) => r,
            _ => panic!("{}: unexpected status", self.name),
        }
    }
}

/// A small frame, numbered.
pub fn frame(sequence: u64) -> Frame {
    Frame {
        image: RgbImage::new(8, 6),
        sequence,
        timestamp: SystemTime::now(),
    }
}

/// A camera whose every `grab_fresh` takes the next scripted reply.
pub struct ScriptedCamera {
    script: VecDeque<Expect<Result<Frame, HwError>>>,
}

pub fn grab(r: Result<Frame, HwError>) -> Expect<Result<Frame, HwError>> {
    Expect {
        call: r,
        effect: None,
    }
}

impl ScriptedCamera {
    pub fn new(script: impl IntoIterator<Item = Expect<Result<Frame, HwError>>>) -> ScriptedCamera {
        ScriptedCamera {
            script: script.into_iter().collect(),
        }
    }
    /// `n` good frames.
    pub fn frames(n: u64) -> ScriptedCamera {
        ScriptedCamera::new((0..n).map(|i| grab(Ok(frame(i)))))
    }
    pub fn done(&self) {
        assert!(
            self.script.is_empty(),
            "camera: {} expected grab(s) were not made",
            self.script.len()
        );
    }
}

impl Camera for ScriptedCamera {
    fn name(&self) -> &str {
        "camera"
    }
    fn size(&self) -> (u32, u32) {
        (8, 6)
    }
    fn grab(&mut self, timeout: Duration) -> Result<Frame, HwError> {
        self.grab_fresh(SystemTime::UNIX_EPOCH, timeout)
    }
    fn grab_fresh(&mut self, _not_before: SystemTime, _t: Duration) -> Result<Frame, HwError> {
        match self.script.pop_front() {
            Some(e) => e.take(),
            None => panic!("camera: unexpected grab: the script is used up"),
        }
    }
}

/// An interferometer log whose readings follow a script, one per frame.
pub struct ScriptedLog {
    readings: VecDeque<Option<f64>>,
    samples: Vec<LogSample>,
}

impl ScriptedLog {
    pub fn new(readings: impl IntoIterator<Item = Option<f64>>) -> ScriptedLog {
        ScriptedLog {
            readings: readings.into_iter().collect(),
            samples: Vec::new(),
        }
    }
}

impl PositionLog for ScriptedLog {
    fn begin(&mut self, _from: SystemTime) {}
    fn position_at(&mut self, t: SystemTime) -> Option<f64> {
        let at = self
            .readings
            .pop_front()
            .unwrap_or_else(|| panic!("log: unexpected reading: the script is used up"));
        if let Some(p) = at {
            let t_unix_s = crate::timestamps::unix_s(t);
            let sample = self.samples.len();
            self.samples.push(LogSample {
                t_unix_s,
                position_um: p,
                sample,
            });
        }
        at
    }
    fn take_samples(&mut self) -> Vec<LogSample> {
        std::mem::take(&mut self.samples)
    }
    fn source(&self) -> LogSource {
        LogSource {
            path: "scripted".into(),
            format: "csv".into(),
            ..LogSource::default()
        }
    }
}

/// A stage that is wherever it was last sent, at once: for tests about what happens after
/// the move (sinks, processing), where the exact calls do not matter.
#[derive(Debug, Default)]
pub struct IdealStage {
    pub position_um: f64,
    pub moves: usize,
    pub stops: usize,
}

impl Stage for IdealStage {
    fn name(&self) -> &str {
        "axis"
    }
    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError> {
        self.move_abs(self.position_um + delta_um)
    }
    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        self.position_um = target_um;
        self.moves += 1;
        Ok(())
    }
    fn wait_settled(&mut self, _timeout: Duration) -> Result<f64, HwError> {
        Ok(self.position_um)
    }
    fn position_um(&mut self) -> Result<f64, HwError> {
        Ok(self.position_um)
    }
    fn stop(&mut self) -> Result<(), HwError> {
        self.stops += 1;
        Ok(())
    }
    fn home(&mut self) -> Result<(), HwError> {
        self.move_abs(0.0)
    }
    fn status(&mut self) -> Result<StageStatus, HwError> {
        Ok(StageStatus {
            state: MotionState::Idle,
            position_um: self.position_um,
        })
    }
}
