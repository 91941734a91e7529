//! Rig requests outside a job (`unlock`, `home`, `reconnect`): checked on the connection,
//! run by the worker on the rig's own blocking thread (the worker owns the rig), answered
//! through a oneshot. `position` and `move` (`daemon::manual`) use the same channel.
//!
//! A request is refused while a job runs; while another request runs it waits its turn in
//! a bounded queue ([`QUEUE`]), in the order sent (a `rigctl jog` user's keys queue their
//! moves). One that was sent before a job started and reaches the worker after is refused. The fault is
//! cleared only when the controller confirms (its status after the request is not
//! `Alarm` and it answered); otherwise the fault is what the controller now says.

use crate::acquisition::StageKind;
use crate::daemon::manual::{self, Target};
use crate::daemon::protocol::{ErrorCode, ProtoError, ReplyBody, RigActionReply};
use crate::daemon::rig_state::{probe, RigAction, RigFault, RigState};
use crate::daemon::Shared;
use crate::hw::devices::panic_free;
use crate::hw::{HwError, MotionState, StageStatus};
use crate::rig::Rig;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use tokio::sync::{mpsc, oneshot};

/// Rig requests waiting for the worker behind the one running, in order; more are refused
/// `busy`.
pub const QUEUE: usize = 8;

/// One rig request on its way to the worker.
#[derive(Debug)]
pub struct RigRequest {
    pub action: RigAction,
    pub stage: StageKind,
    /// `RigCondition::jobs_started` when it was checked.
    pub jobs_started: u64,
    /// Where a `move` goes.
    pub target: Option<Target>,
    /// `ManualState`'s stop count when it was sent: a `stop` since then stops the move.
    pub stops_seen: u64,
    pub reply: oneshot::Sender<Result<ReplyBody, ProtoError>>,
}

pub type Sender = mpsc::Sender<RigRequest>;
pub type Receiver = mpsc::Receiver<RigRequest>;

fn busy(msg: String) -> ProtoError {
    ProtoError::new(ErrorCode::Busy, msg)
}

/// The connection's side: check, hand to the worker, wait for its answer.
pub async fn request(
    shared: &Arc<Shared>,
    action: RigAction,
    stage: Option<StageKind>,
) -> Result<ReplyBody, ProtoError> {
    send(shared, action, stage, None).await
}

/// Any rig request, `move` with its target.
pub async fn send(
    shared: &Arc<Shared>,
    action: RigAction,
    stage: Option<StageKind>,
    target: Option<Target>,
) -> Result<ReplyBody, ProtoError> {
    if shared.shutting_down.load(Ordering::SeqCst) {
        return Err(ProtoError::new(
            ErrorCode::Unavailable,
            "the daemon is shutting down",
        ));
    }
    let running = {
        let jobs = shared.jobs();
        jobs.running()
            .map(|id| (id, jobs.get(id).map(|r| r.stop.pause.state())))
    };
    if let Some((id, pause)) = running {
        return Err(busy(match pause {
            Some(crate::acquisition::PauseState::Paused) => format!(
                "`{}` is refused: job {id} is paused and owns the stage (resume it: \
                 rigctl resume {id}, or cancel it: rigctl cancel {id}; then ask again)",
                action.name()
            ),
            _ => format!(
                "`{}` is refused: job {id} is running (ask again when it ends, or cancel it: \
                 rigctl cancel {id})",
                action.name()
            ),
        }));
    }
    let (tx, rx) = oneshot::channel();
    let req = {
        let cond = shared.rig();
        let stage = stage.unwrap_or_else(|| default_stage(cond.fault.as_ref()));
        RigRequest {
            action,
            stage,
            jobs_started: cond.jobs_started,
            target,
            stops_seen: shared.manual.stops(),
            reply: tx,
        }
    };
    // Counted before it is sent: the worker uncounts it when it takes it.
    let is_move = action == RigAction::Move;
    if is_move {
        shared.manual.move_queued();
    }
    if shared.rig_requests.try_send(req).is_err() {
        if is_move {
            shared.manual.move_dequeued();
        }
        return Err(busy(format!(
            "{QUEUE} rig requests are already waiting: send `{}` again once they have run",
            action.name()
        )));
    }
    match rx.await {
        Ok(r) => r,
        Err(_) => Err(ProtoError::new(
            ErrorCode::Unavailable,
            "the daemon stopped before the request ran",
        )),
    }
}

/// The stage in fault, else the axis.
fn default_stage(fault: Option<&RigFault>) -> StageKind {
    match fault.map(|f| f.device.as_str()) {
        Some("piezo") => StageKind::Piezo,
        _ => StageKind::Axis,
    }
}

/// The worker's side: run the request on the rig (on a blocking thread) and answer it.
pub async fn serve(shared: &Arc<Shared>, rig: Rig, req: RigRequest) -> Rig {
    {
        let mut cond = shared.rig();
        // Uncounted under the lock that marks it running, so a `position` never sees the
        // move neither waiting nor running.
        if req.action == RigAction::Move {
            shared.manual.move_dequeued();
        }
        if cond.jobs_started != req.jobs_started {
            let _ = req.reply.send(Err(busy(format!(
                "a job started before `{}` could run: send it again once the job ends",
                req.action.name()
            ))));
            return rig;
        }
        cond.request = Some(req.action);
    }
    if matches!(req.action, RigAction::Position | RigAction::Move) {
        return manual_serve(shared, rig, req).await;
    }
    let (action, stage) = (req.action, req.stage);
    tracing::info!(request = action.name(), %stage, "rig request");
    let (sh, seen) = (shared.clone(), req.stops_seen);
    let handle = tokio::task::spawn_blocking(move || {
        let mut rig = rig;
        let stopped = || sh.manual.stopped_since(seen);
        let device = stage.to_string();
        let result = panic_free(&device, || act(&mut rig, action, stage, &stopped));
        // The controller's word on the stage, whatever the request did.
        let fault = match &result {
            Ok(_) => None,
            Err(_) => probe(&mut rig, stage),
        };
        (rig, result, fault)
    });
    let (rig, result, fault) = match handle.await {
        Ok(r) => r,
        Err(e) => panic!("rig request thread panicked: {e}"),
    };
    let state = {
        let mut cond = shared.rig();
        cond.request = None;
        let name = stage.to_string();
        if cond.fault.as_ref().is_none_or(|f| f.device == name) {
            cond.fault = fault;
        }
        cond.state(None)
    };
    let reply = match result {
        Ok(st) => {
            tracing::info!(request = action.name(), %stage, at_um = st.position_um, "rig request done");
            Ok(ReplyBody::RigAction(RigActionReply {
                request: action,
                stage,
                state: st.state,
                position_um: st.position_um,
                rig_state: state,
            }))
        }
        Err(e) => {
            tracing::warn!(request = action.name(), %stage, "rig request failed: {e}");
            Err(ProtoError::new(
                ErrorCode::Hardware,
                format!("{} failed: {e}", action.name()),
            ))
        }
    };
    let _ = req.reply.send(reply);
    rig
}

/// The request on the stage, then its status: the controller's confirmation. A homing
/// cycle stops on a `stop` sent after the request (`stopped()`).
fn act(
    rig: &mut Rig,
    action: RigAction,
    stage: StageKind,
    stopped: &dyn Fn() -> bool,
) -> Result<StageStatus, HwError> {
    let s = rig.stage(stage)?;
    match action {
        RigAction::Unlock => s.unlock()?,
        RigAction::Home if stopped() => {
            return Err(HwError::Other {
                device: s.name().to_string(),
                message: "not homed: a `stop` came before the homing cycle started".into(),
            })
        }
        RigAction::Home => {
            if s.home_stoppable(stopped)? {
                return Err(homing_stopped(s));
            }
        }
        RigAction::Reconnect => s.reconnect()?,
        RigAction::Position | RigAction::Move => unreachable!("served by manual_serve"),
    }
    let st = s.status()?;
    if st.state == MotionState::Alarm {
        return Err(HwError::Alarm {
            device: s.name().to_string(),
            code: 0,
            message: format!(
                "still in alarm after `{}` (at {:.1} µm)",
                action.name(),
                st.position_um
            ),
        });
    }
    Ok(st)
}

/// What a homing cycle stopped by `stop` left: the stage as it reports now (GRBL: in alarm
/// after the soft reset that aborts homing).
fn homing_stopped(s: &mut dyn crate::hw::Stage) -> HwError {
    let now = match s.status() {
        Ok(st) => format!(
            "{} at {:.1} µm",
            crate::acquisition::outcome::state_name(st.state),
            st.position_um
        ),
        Err(e) => format!("not reporting ({e})"),
    };
    HwError::Other {
        device: s.name().to_string(),
        message: format!(
            "homing stopped by `stop` (aborted the controller's way: GRBL's soft reset leaves \
             it in alarm); now {now}: unlock or home it again"
        ),
    }
}

/// `position` and `move` on the rig's blocking thread. A move that fails on the hardware
/// leaves the fault the controller now says, as the other requests do.
async fn manual_serve(shared: &Arc<Shared>, rig: Rig, req: RigRequest) -> Rig {
    let (stage, target, stops_seen) = (req.stage, req.target, req.stops_seen);
    let sh = shared.clone();
    let handle = tokio::task::spawn_blocking(move || {
        let mut rig = rig;
        let Some(t) = target else {
            let p = manual::read_position(&mut rig);
            return (rig, Ok(ReplyBody::Position(p)), None);
        };
        let device = stage.to_string();
        let r = panic_free(&device, || {
            manual::run_move(&sh.manual, &mut rig, stage, t, stops_seen)
        });
        sh.manual.clear_last();
        let fault = match &r {
            Err(e) if !matches!(e, HwError::Limit { .. }) => probe(&mut rig, stage),
            _ => None,
        };
        let r = r.map(|(target_um, st, stopped)| {
            tracing::info!(%stage, target_um, at_um = st.position_um, stopped, "manual move");
            ReplyBody::Move(manual::MoveReply {
                stage,
                target_um,
                position_um: st.position_um,
                state: st.state,
                stopped,
                rig_state: RigState::Ready,
            })
        });
        (rig, r.map_err(manual::move_error), fault)
    });
    let (rig, mut reply, fault) = handle.await.expect("manual request thread panicked");
    {
        let mut cond = shared.rig();
        cond.request = None;
        if fault.is_some() {
            cond.fault = fault;
        }
        let state = cond.state(None);
        match &mut reply {
            Ok(ReplyBody::Position(p)) => p.rig_state = state,
            Ok(ReplyBody::Move(m)) => m.rig_state = state,
            _ => {}
        }
    }
    let _ = req.reply.send(reply);
    rig
}

/// Refuse what is waiting (the daemon stops).
pub fn refuse_waiting(rx: &mut Receiver) {
    while let Ok(req) = rx.try_recv() {
        let _ = req.reply.send(Err(ProtoError::new(
            ErrorCode::Unavailable,
            "the daemon is shutting down",
        )));
    }
}
