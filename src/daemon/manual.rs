//! Manual control outside a job: `position`, `move`, `stop`. `position` and
//! `move` run on the worker like the other rig requests (`rig_commands`: the worker owns
//! the rig); `stop` does not queue behind the move it stops: it sets a flag the move's
//! wait polls, as a job's cancel does.
//!
//! While a move runs, `position` answers from the move's own last poll; while a job is
//! paused, from where the job left its stage (the job owns the rig: nothing else is read).
//! Moves are refused while any job runs or is paused (a paused job owns the stage's
//! position: its next frame is planned from it) and while the rig is in fault. The soft
//! limits and `max_step_um` are the drivers' (`hw::limits::check_move`, from the stage's
//! last target): a refused move names the limit and moves nothing.

use crate::acquisition::{PauseState, StageKind};
use crate::daemon::protocol::{ErrorCode, ProtoError, ReplyBody, Request};
use crate::daemon::rig_commands;
use crate::daemon::rig_state::{RigAction, RigState};
use crate::daemon::Shared;
use crate::hw::{HwError, MotionState, StageStatus};
use crate::rig::Rig;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Between status polls of a manual move: how late a `stop` stops it, at most.
const MOVE_POLL: Duration = Duration::from_millis(5);
/// How long a manual move may take.
const MOVE_TIMEOUT: Duration = Duration::from_secs(60);

/// Where a move goes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Target {
    To(f64),
    By(f64),
}

/// One stage as its controller reported it (or why it could not).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct StageReading {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position_um: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state: Option<MotionState>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

impl StageReading {
    fn of(r: Result<StageStatus, HwError>) -> StageReading {
        match r {
            Ok(st) => StageReading {
                position_um: Some(st.position_um),
                state: Some(st.state),
                error: None,
            },
            Err(e) => StageReading {
                position_um: None,
                state: None,
                error: Some(e.to_string()),
            },
        }
    }
}

/// The interferometer read once, outside a job (or why it could not be).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct LaserReading {
    /// The laser's reading, µm (its own datum and sign, as in the session's
    /// `interferometer.csv`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position_um: Option<f64>,
    /// When it was taken (s since the epoch, PC clock).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub t_unix_s: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

impl LaserReading {
    fn of(r: Result<crate::hw::devices::LogSample, String>) -> LaserReading {
        match r {
            Ok(s) => LaserReading {
                position_um: Some(s.position_um),
                t_unix_s: Some(s.t_unix_s),
                error: None,
            },
            Err(e) => LaserReading {
                position_um: None,
                t_unix_s: None,
                error: Some(e),
            },
        }
    }
}

/// Where the reading comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum PositionSource {
    /// Asked of the controllers now.
    Controllers,
    /// A manual move runs: its last poll of the moving stage (the other read at its start).
    Move,
    /// A job is paused: where it left its stage (the other stage is not read).
    PausedJob,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct PositionReply {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis: Option<StageReading>,
    /// Absent on a rig without a piezo (and when not read).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub piezo: Option<StageReading>,
    /// The interferometer, read with the controllers (`source` `controllers`); absent on a
    /// rig without one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub interferometer: Option<LaserReading>,
    pub source: PositionSource,
    /// The paused job, when the reading is where it left its stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job_id: Option<u64>,
    pub rig_state: RigState,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct MoveReply {
    pub stage: StageKind,
    pub target_um: f64,
    /// Where the stage ended, as its controller reports it.
    pub position_um: f64,
    pub state: MotionState,
    /// A `stop` ended the move short of its target.
    pub stopped: bool,
    pub rig_state: RigState,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct StopReply {
    /// A manual move was under way and is told to stop (its own reply says where it ended).
    pub stopping: bool,
    pub message: String,
}

/// The daemon's side of manual moves: the stops sent, the moves waiting, the running
/// move's last poll.
#[derive(Debug, Default)]
pub struct ManualState {
    /// `stop`s sent so far: a move stops (or never starts) when a stop came after it was sent.
    stops: AtomicU64,
    /// Moves queued behind the running rig request.
    waiting: AtomicUsize,
    last: Mutex<Option<(StageReading, StageReading, StageKind)>>,
}

impl ManualState {
    pub fn stops(&self) -> u64 {
        self.stops.load(Ordering::SeqCst)
    }
    /// Whether a stop came after a move sent when `stops()` was `seen`.
    pub fn stopped_since(&self, seen: u64) -> bool {
        self.stops() != seen
    }
    pub fn move_queued(&self) {
        self.waiting.fetch_add(1, Ordering::SeqCst);
    }
    pub fn move_dequeued(&self) {
        let _ = self
            .waiting
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1));
    }
    fn set_last(&self, v: Option<(StageReading, StageReading, StageKind)>) {
        *self.last.lock().unwrap_or_else(|e| e.into_inner()) = v;
    }
    /// The move ended: nothing to report from it.
    pub fn clear_last(&self) {
        self.set_last(None);
    }
    fn last(&self) -> Option<(StageReading, StageReading, StageKind)> {
        self.last.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

/// Whether the connection hands this request here.
pub fn is_manual(req: &Request) -> bool {
    matches!(
        req,
        Request::Position {} | Request::Move { .. } | Request::Stop {}
    )
}

/// The connection's side of `position`, `move` and `stop`.
pub async fn handle(shared: &Arc<Shared>, req: Request) -> Result<ReplyBody, ProtoError> {
    match req {
        Request::Position {} => position(shared).await,
        Request::Move {
            stage,
            to_um,
            by_um,
        } => {
            let target = target_of(to_um, by_um)?;
            if let Some(f) = shared.rig().fault.clone() {
                return Err(ProtoError::new(ErrorCode::Rejected, f.refusal()));
            }
            // A stop sent from here on stops this move, running or waiting.
            rig_commands::send(shared, RigAction::Move, Some(stage), Some(target)).await
        }
        Request::Stop {} => Ok(ReplyBody::Stop(stop(shared))),
        _ => Err(ProtoError::new(ErrorCode::Internal, "not a manual request")),
    }
}

fn target_of(to_um: Option<f64>, by_um: Option<f64>) -> Result<Target, ProtoError> {
    let bad = |m: &str| ProtoError::new(ErrorCode::BadRequest, m);
    match (to_um, by_um) {
        (Some(t), None) if t.is_finite() => Ok(Target::To(t)),
        (None, Some(d)) if d.is_finite() => Ok(Target::By(d)),
        (Some(_), None) => Err(bad("`to_um` must be a finite number of µm")),
        (None, Some(_)) => Err(bad("`by_um` must be a finite number of µm")),
        (Some(_), Some(_)) => Err(bad(
            "give `to_um` (absolute) or `by_um` (relative), not both",
        )),
        (None, None) => Err(bad(
            "a move needs `to_um` (absolute, µm) or `by_um` (relative, µm)",
        )),
    }
}

/// A running move's poll, a paused job's stage, or the controllers asked by the worker.
async fn position(shared: &Arc<Shared>) -> Result<ReplyBody, ProtoError> {
    let running = {
        let jobs = shared.jobs();
        jobs.running()
            .and_then(|id| jobs.get(id).map(|r| (id, r.stop.clone(), r.spec.stage)))
    };
    if let Some((id, flag, stage)) = running {
        if flag.pause.state() != PauseState::Paused {
            return Err(ProtoError::new(
                ErrorCode::Busy,
                format!(
                    "job {id} is running and owns the rig: its `step` events give the \
                     positions (pause it to read them: rigctl pause {id})"
                ),
            ));
        }
        let reading = StageReading {
            position_um: flag.pause.at_um(),
            state: Some(MotionState::Idle),
            error: None,
        };
        let reading = Some(reading);
        let (axis, piezo) = match stage {
            StageKind::Axis => (reading, None),
            StageKind::Piezo => (None, reading),
        };
        return Ok(ReplyBody::Position(PositionReply {
            axis,
            piezo,
            interferometer: None,
            source: PositionSource::PausedJob,
            job_id: Some(id),
            rig_state: shared.rig_state(),
        }));
    }
    if let Some(reading) = move_reading(shared).await {
        return Ok(move_reply(shared, reading));
    }
    // A move sent meanwhile may get ahead of this request in the worker's queue: answer
    // from its first reading then, rather than wait for the whole move.
    tokio::select! {
        r = rig_commands::send(shared, RigAction::Position, None, None) => r,
        reading = move_begun(shared) => Ok(move_reply(shared, reading)),
    }
}

/// `position`'s reply from a running move's reading.
fn move_reply(
    shared: &Shared,
    (axis, piezo, _): (StageReading, StageReading, StageKind),
) -> ReplyBody {
    ReplyBody::Position(PositionReply {
        axis: Some(axis),
        piezo: shared.rig_info.piezo_limits_um.map(|_| piezo),
        interferometer: None,
        source: PositionSource::Move,
        job_id: None,
        rig_state: shared.rig_state(),
    })
}

/// The first reading of a manual move that starts from now on (pending while none runs).
async fn move_begun(shared: &Shared) -> (StageReading, StageReading, StageKind) {
    loop {
        let moving = shared.rig().request == Some(RigAction::Move);
        if let Some(last) = shared.manual.last().filter(|_| moving) {
            return last;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// The running manual move's latest reading. A move that has just been handed to the worker
/// has none until its first poll (every 5 ms), and one sent but not yet taken by the worker
/// has not started: wait for its first poll rather than queue behind the whole move.
async fn move_reading(shared: &Shared) -> Option<(StageReading, StageReading, StageKind)> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(2);
    loop {
        let (moving, waiting) = {
            let cond = shared.rig();
            let waiting = shared.manual.waiting.load(Ordering::SeqCst);
            (cond.request == Some(RigAction::Move), waiting)
        };
        if !moving && waiting == 0 {
            break;
        }
        if let Some(last) = shared.manual.last().filter(|_| moving) {
            return Some(last);
        }
        if tokio::time::Instant::now() >= deadline {
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    None
}

fn stop(shared: &Shared) -> StopReply {
    if let Some(id) = shared.jobs().running() {
        return StopReply {
            stopping: false,
            message: format!(
                "no manual move runs: job {id} does (stop it with rigctl cancel {id}, or \
                 rigctl pause {id})"
            ),
        };
    }
    shared.manual.stops.fetch_add(1, Ordering::SeqCst);
    let request = shared.rig().request;
    if request == Some(RigAction::Home) {
        return StopReply {
            stopping: true,
            message: "stopping the homing cycle: GRBL aborts it by a soft reset, which leaves \
                      the axis in alarm (rigctl unlock, or home again)"
                .into(),
        };
    }
    let running = request == Some(RigAction::Move);
    let waiting = shared.manual.waiting.load(Ordering::SeqCst);
    let waiting_text = match waiting {
        0 => String::new(),
        1 => "; the move waiting behind it does not run".into(),
        n => format!("; the {n} moves waiting behind it do not run"),
    };
    match (running, waiting) {
        (true, _) => StopReply {
            stopping: true,
            message: format!("stopping the manual move{waiting_text}"),
        },
        (false, 0) => StopReply {
            stopping: false,
            message: "no manual move runs: nothing to stop".into(),
        },
        (false, n) => StopReply {
            stopping: true,
            message: format!("no manual move runs yet: the {n} waiting do not run"),
        },
    }
}

/// The worker's side of `position`, on the rig's blocking thread.
pub fn read_position(rig: &mut Rig) -> PositionReply {
    let axis = StageReading::of(rig.axis.status());
    let piezo = rig.piezo.as_mut().map(|p| StageReading::of(p.status()));
    let interferometer = rig
        .log
        .as_deref_mut()
        .map(|l| LaserReading::of(l.reading_now()));
    PositionReply {
        axis: Some(axis),
        piezo,
        interferometer,
        source: PositionSource::Controllers,
        job_id: None,
        rig_state: RigState::Ready,
    }
}

/// The worker's side of `move`: start it (the driver checks the limits), wait for its end
/// polling for a `stop`; a stop halts the stage where it is.
pub fn run_move(
    state: &ManualState,
    rig: &mut Rig,
    kind: StageKind,
    target: Target,
    stops_seen: u64,
) -> Result<(f64, StageStatus, bool), HwError> {
    let other = match kind {
        StageKind::Axis => rig.piezo.as_mut().map(|p| StageReading::of(p.status())),
        StageKind::Piezo => Some(StageReading::of(rig.axis.status())),
    }
    .unwrap_or(StageReading {
        position_um: None,
        state: None,
        error: None,
    });
    let stage = rig.stage(kind)?;
    if state.stopped_since(stops_seen) {
        // Stopped while it waited for its turn: it does not start.
        let st = stage.status()?;
        let target_um = match target {
            Target::To(t) => t,
            Target::By(d) => st.position_um + d,
        };
        return Ok((target_um, st, true));
    }
    let target_um = match target {
        Target::To(t) => {
            stage.move_abs(t)?;
            t
        }
        Target::By(d) => {
            let from = stage.status()?.position_um;
            stage.move_rel(d)?;
            from + d
        }
    };
    let deadline = Instant::now() + MOVE_TIMEOUT + stage.planned_move().unwrap_or_default();
    let result = loop {
        let st = stage.status()?;
        let reading = StageReading::of(Ok(st.clone()));
        state.set_last(Some(match kind {
            StageKind::Axis => (reading, other.clone(), kind),
            StageKind::Piezo => (other.clone(), reading, kind),
        }));
        if state.stopped_since(stops_seen) {
            stage.stop()?;
            break (target_um, stage.status()?, true);
        }
        match st.state {
            MotionState::Moving | MotionState::Homing => {}
            MotionState::Idle => {
                let left = deadline.saturating_duration_since(Instant::now());
                let at = stage.wait_settled(left.max(Duration::from_millis(1)))?;
                break (
                    target_um,
                    StageStatus {
                        position_um: at,
                        ..st
                    },
                    false,
                );
            }
            MotionState::Holding | MotionState::Alarm => {
                let _ = stage.stop();
                return Err(HwError::Other {
                    device: stage.name().to_string(),
                    message: format!(
                        "the move to {target_um} µm ended {} at {:.1} µm",
                        if st.state == MotionState::Alarm {
                            "in alarm"
                        } else {
                            "in a feed hold"
                        },
                        st.position_um
                    ),
                });
            }
        }
        if Instant::now() >= deadline {
            let _ = stage.stop();
            return Err(HwError::NotSettled {
                device: stage.name().to_string(),
                timeout_ms: MOVE_TIMEOUT.as_millis() as u64,
                state: format!("still {:?} at {:.1} µm", st.state, st.position_um),
            });
        }
        std::thread::sleep(MOVE_POLL);
    };
    Ok(result)
}

/// A move's error as the client reads it: a limit is a refusal naming it, the rest the
/// hardware's.
pub fn move_error(e: HwError) -> ProtoError {
    match e {
        HwError::Limit { .. } => ProtoError::new(ErrorCode::Rejected, e.to_string()),
        e => ProtoError::new(ErrorCode::Hardware, format!("move failed: {e}")),
    }
}
